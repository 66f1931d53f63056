/* Pure board logic of the STM32 layer: no register access, so the host can compile and test
 * it (tests/test_firmware_board.py loads it with ctypes). Every number here is from RM0390
 * (STM32F446 reference manual), the STM32F446 datasheet or the Nucleo-64 manual UM1724; the
 * sections are named in docs/hardware.md. */
#ifndef ML_BOARD_LOGIC_H
#define ML_BOARD_LOGIC_H

#include <stdbool.h>
#include <stdint.h>

/* RCC_CSR reset flags (RM0390, RCC_CSR): set by hardware, cleared by writing RMVF. */
#define RCC_CSR_RMVF (1u << 24)
#define RCC_CSR_BORRSTF (1u << 25)
#define RCC_CSR_PINRSTF (1u << 26)
#define RCC_CSR_PORRSTF (1u << 27)
#define RCC_CSR_SFTRSTF (1u << 28)
#define RCC_CSR_IWDGRSTF (1u << 29)
#define RCC_CSR_WWDGRSTF (1u << 30)
#define RCC_CSR_LPWRRSTF (1u << 31)

/* The protocol's `rst` word for the flags of one boot. Every internal reset also pulses the
 * NRST pin (PINRSTF set too) and a power-on also sets BORRSTF, so the most specific flag wins:
 * watchdog, then power-on, then brown-out, then software, then pin; none (or only the
 * low-power-management flag) is "unknown". */
const char *reset_cause_word(uint32_t rcc_csr);

/* Interlock debounce: the reported state changes only after at least `need_samples`
 * consecutive equal samples spanning at least `need_us`. Starts open (the safe state). */
typedef struct {
    bool stable_open; /* the debounced state */
    bool cand_open;   /* the state the recent samples agree on */
    uint32_t cand_since_us;
    uint32_t cand_count;
} debounce_t;

void debounce_init(debounce_t *d, bool open, uint32_t now_us);
/* One raw sample (true = open) at now_us (a wrapping 32-bit µs clock); the debounced state. */
bool debounce_step(debounce_t *d, bool raw_open, uint32_t now_us, uint32_t need_us,
                   uint32_t need_samples);

/* DAC: 12-bit codes kept inside the output buffer's linear range, 0.2 V .. VDDA - 0.2 V
 * (datasheet DS10693, DAC characteristics, buffer on): at VDDA = 3.3 V and
 * V = VDDA * code / 4095 that is codes 249 .. 3846; symmetric about mid-scale 2048 it is
 * 2048 -/+ 1798. One code is 2*fsv/4096 at the amplifier input (the protocol's LSB). */
#define DAC_MID 2048u
#define DAC_SPAN 1798u
#define DAC_CODE_MIN (DAC_MID - DAC_SPAN)
#define DAC_CODE_MAX (DAC_MID + DAC_SPAN)
/* The code for drive v (V at the amplifier input) with full scale fsv (V); *clamped is set
 * when v lay outside the linear range (never, when the limits fit: see main.c). */
uint32_t dac_code(float v, float fsv, bool *clamped);
/* True if a signed code (around mid-scale) lies inside the linear range. */
bool dac_code_linear(int32_t signed_code);
/* Largest drive (µV) that stays inside the linear range for full scale fsv_uv. */
int64_t dac_linear_max_uv(int64_t fsv_uv);

/* PLL for 168 MHz from an in_hz clock: PLLM so the VCO input is 2 MHz (RM0390, RCC_PLLCFGR:
 * 1-2 MHz, 2 MHz recommended to limit jitter), PLLN = 168 (VCO 336 MHz), PLLP = /2, PLLQ = 7, PLLR = 2.
 * 0 if in_hz is not a whole multiple of 2 MHz in 4..26 MHz. */
uint32_t pll_cfgr_168mhz(uint32_t in_hz, bool hse);

/* DMA1/2 stream n (0..7): which flag-clear register (0 = LIFCR, 1 = HIFCR) and the mask of
 * all five of its flags (FEIF, DMEIF, TEIF, HTIF, TCIF; RM0390, DMA_LIFCR/HIFCR). */
uint32_t dma_stream_flag_mask(unsigned stream, unsigned *high_register);

/* Attenuator steps: parse "0,20,40" (ascending, first 0, at most ATT_MAX_STEPS); the count,
 * 0 if malformed. */
#define ATT_MAX_STEPS 4u
unsigned att_parse(const char *list, uint8_t steps_db[ATT_MAX_STEPS]);
/* The level of each of the two control lines for step index `step` of `count`, bit 0 = line
 * A, bit 1 = line B. Lines carry (count - 1 - step) in binary: all low (the reset state, with
 * pull-downs on the relay drivers) selects the LARGEST attenuation, so a board in reset or
 * unpowered never leaves the amplifier on the 0 dB path. */
uint32_t att_line_code(unsigned step, unsigned count);

#endif
