/* QEMU outputs: QEMU's STM32F405 has no DAC, DMA, GPIO or IWDG model, so samples rendered at
 * the sample rate are recorded in a RAM ring (inspect with gdb: `x/64f ram_out_ev`) and DIAG
 * reports the last ones. The interlock input is a second UART (QEMU serial1 = USART2): a byte
 * 'o' opens it, 'c' closes it, like a test rig toggling a relay; it goes through the same
 * debounce as the board's PC8. The attenuator steps and IWDG feeds are recorded in RAM. */
#include "../core/board.h"
#include "board_logic.h"
#include "regs.h"
#include "stm32.h"

#define RING 1024u
#define BATCH 32u

float ram_out_ev[RING], ram_out_mv[RING];
volatile uint32_t ram_out_count;   /* samples recorded since boot */
volatile uint32_t ram_out_skipped; /* samples not recorded: emulation slower than fs */
static uint64_t next_sample;
static bool il_open;
static debounce_t interlock;
volatile uint32_t iwdg_feeds;      /* the modelled IWDG: feeds since boot */
volatile uint8_t ram_att_step[2];  /* last attenuator step per channel */
static uint8_t att_steps[ATT_MAX_STEPS];
static unsigned att_count;

void output_init(fw_t *fw)
{
    next_sample = board_mono_us() * fw->cfg.fs_hz / 1000000u;
}

void output_service(fw_t *fw)
{
    uint32_t fs = fw->cfg.fs_hz;
    uint64_t now = board_mono_us() * fs / 1000000u;
    if (!output_active(fw)) {
        if (ram_out_count && (ram_out_ev[(ram_out_count - 1u) % RING] != 0.0f ||
                              ram_out_mv[(ram_out_count - 1u) % RING] != 0.0f)) {
            output_emergency_zero(); /* the trial ended: the outputs rest at 0 V */
        }
        next_sample = now + 1; /* silence needs no rendering */
        return;
    }
    /* At most BATCH samples per call, so the main loop (watchdog, trial steps, UART) stays
     * responsive even when emulation runs slower than the sample rate; behind by more,
     * the recording skips ahead (it is a diagnostic record, the DAC board never skips). */
    if (now >= next_sample + BATCH) {
        ram_out_skipped += (uint32_t)(now + 1u - BATCH - next_sample);
        next_sample = now + 1u - BATCH;
    }
    for (; next_sample <= now; next_sample++) {
        float v[2];
        fw_render(fw, (int64_t)(next_sample * 1000000u / fs), v);
#if FW_PROTOCOL_VERSION >= 2
        if (!board_codes_playable(fw)) {
            fw_refill_end(fw);
            return; /* the same linear-range rule as the DAC board */
        }
#endif
        ram_out_ev[ram_out_count % RING] = v[0];
        ram_out_mv[ram_out_count % RING] = v[1];
        ram_out_count++;
    }
    fw_refill_end(fw); /* the refill's work, measured before the loop may sleep */
}

bool output_active(const fw_t *fw)
{
    return fw->playing || fw->amp_uv[0] > 0 || fw->amp_uv[1] > 0;
}

void output_emergency_zero(void)
{
    ram_out_ev[ram_out_count % RING] = 0.0f;
    ram_out_mv[ram_out_count % RING] = 0.0f;
    ram_out_count++;
}

void board_outputs_zero(void)
{
    output_emergency_zero();
}

void board_dac_last(float out[2])
{
    uint32_t i = (ram_out_count + RING - 1u) % RING;
    out[0] = ram_out_ev[i];
    out[1] = ram_out_mv[i];
}

void hw_watchdog_init(void)
{
    iwdg_feeds = 0;
}

void board_iwdg_feed(void)
{
    iwdg_feeds++;
}

void attenuator_init(void)
{
    att_count = att_parse(ATT_STEPS_DB, att_steps);
    ram_att_step[0] = ram_att_step[1] = (uint8_t)(att_count ? att_count - 1u : 0u);
}

void board_set_attenuator(int ch, uint8_t step_index)
{
    if (ch >= 0 && ch <= 1 && step_index < att_count) {
        ram_att_step[ch] = step_index;
    }
}

static bool interlock_raw_open(void);


void interlock_init(void)
{
    rcc_enable(&RCC_APB1ENR, 1u << 17); /* USART2 */
    USART_CR1(USART2_BASE) = USART_CR1_UE | USART_CR1_RE;
    il_open = false;
    uint32_t t0 = board_micros32();
    debounce_init(&interlock, true, t0);
    while ((uint32_t)(board_micros32() - t0) < 4u * INTERLOCK_DEBOUNCE_US) {
        (void)interlock_read_open();
    }
}

bool interlock_read_open(void)
{
    return debounce_step(&interlock, interlock_raw_open(), board_micros32(),
                         INTERLOCK_DEBOUNCE_US, INTERLOCK_DEBOUNCE_SAMPLES);
}

static bool interlock_raw_open(void)
{
    while (USART_SR(USART2_BASE) & USART_SR_RXNE) {
        uint8_t b = (uint8_t)USART_DR(USART2_BASE);
        if (b == 'o') {
            il_open = true;
        } else if (b == 'c') {
            il_open = false;
        }
    }
    return il_open;
}
