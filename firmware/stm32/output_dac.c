/* Real board outputs: DAC1 (PA4) = EV, DAC2 (PA5) = MV, both converted on every TIM6 update
 * (20 kHz) from one circular DMA buffer of dual-channel words (DHR12RD), refilled from the
 * main loop a few ms ahead of the DMA read position. Mid-scale (2048) is 0 V drive: the
 * input stage subtracts the reference (docs/hardware.md); codes stay inside the DAC buffer's
 * linear range (board_logic.h). Also the IWDG, the interlock input (PC8, pull-up: an open
 * loop or a broken wire reads open; debounced) and the attenuator control lines. */
#include "../core/board.h"
#include "board_logic.h"
#include "regs.h"
#include "stm32.h"

#define BUF_SAMPLES 512u         /* 25.6 ms at 20 kHz */
#define LEAD_SAMPLES 200u        /* keep ~10 ms rendered ahead of the DMA */
#define MID_WORD ((DAC_MID << 16) | DAC_MID)
#define DMA_STREAM 5u /* DMA1 stream 5 channel 7 = DAC1 request (RM0390, DMA1 request mapping) */

static volatile uint32_t dma_buf[BUF_SAMPLES];
static uint64_t next_sample;     /* absolute index of the next sample to render */
static uint64_t dma_start_us;    /* device time of sample 0 */
static uint32_t last_pos;
static uint64_t wraps;
static float last_v[2];

#if FW_PROTOCOL_VERSION < 2
static const float fsv_v[2] = {(float)FSV_EV_UV / 1e6f, (float)FSV_MV_UV / 1e6f};
extern volatile uint32_t dac_clamped;

static uint32_t to_code(int ch, float v)
{
    bool clamped;
    uint32_t code = dac_code(v, fsv_v[ch], &clamped);
    dac_clamped += clamped ? 1u : 0u;
    return code;
}
#endif

static void dma_clear_flags(void)
{
    unsigned high;
    uint32_t mask = dma_stream_flag_mask(DMA_STREAM, &high);
    if (high) {
        DMA1_HIFCR = mask;
    } else {
        DMA1_LIFCR = mask;
    }
}

static uint64_t read_position(void)
{
    uint32_t pos = BUF_SAMPLES - DMA1_S5NDTR;
    if (pos < last_pos) {
        wraps++;
    }
    last_pos = pos;
    return wraps * BUF_SAMPLES + pos;
}

void output_init(fw_t *fw)
{
    (void)fw;
    rcc_enable(&RCC_AHB1ENR, 1u | (1u << 21));       /* GPIOA, DMA1 */
    rcc_enable(&RCC_APB1ENR, (1u << 29) | (1u << 4)); /* DAC, TIM6 */
    GPIO_MODER(GPIOA_BASE) |= (3u << 8) | (3u << 10); /* PA4, PA5 analog */
    TIM6_CR1 = 0;
    DMA1_S5CR = 0;
    while (DMA1_S5CR & 1u) {
        /* a transfer in progress finishes first (RM0390, stream configuration procedure) */
    }
    dma_clear_flags(); /* flags left from the last run would block the re-enabled stream */
    for (uint32_t i = 0; i < BUF_SAMPLES; i++) {
        dma_buf[i] = MID_WORD;
    }
    DAC_DHR12RD = MID_WORD;
    /* both channels: enable, trigger TIM6 TRGO (TSEL=000), ch1 DMA request */
    DAC_CR = (1u << 0) | (1u << 2) | (1u << 12) | (1u << 16) | (1u << 18);
    DMA1_S5PAR = (uint32_t)&DAC_DHR12RD;
    DMA1_S5M0AR = (uint32_t)dma_buf;
    DMA1_S5NDTR = BUF_SAMPLES;
    /* channel 7, 32-bit mem/periph, memory increment, circular, memory-to-peripheral */
    DMA1_S5CR = (7u << 25) | (2u << 13) | (2u << 11) | (1u << 10) | (1u << 8) | (1u << 6);
    DMA1_S5CR |= 1u;
    TIM6_PSC = 0;
    TIM6_ARR = 84000000u / 20000u - 1u; /* APB1 timer clock 84 MHz */
    TIM6_CR2 = (2u << 4);               /* TRGO on update */
    last_pos = 0;
    wraps = 0;
    next_sample = 0;
    dma_start_us = board_mono_us();
    TIM6_CR1 = 1u;
}

void output_service(fw_t *fw)
{
    uint64_t read = read_position();
    if (next_sample < read) {
        next_sample = read; /* fell behind: those samples already played (as rendered before) */
    }
    uint32_t fs = fw->cfg.fs_hz;
    while (next_sample < read + LEAD_SAMPLES) {
        int64_t t_us = (int64_t)(dma_start_us + next_sample * 1000000u / fs);
        float v[2];
        fw_render(fw, t_us, v);
#if FW_PROTOCOL_VERSION >= 2
        /* the core's own quantised codes: exactly the amplitude DONE reports */
        uint32_t ev = DAC_MID, mv = DAC_MID;
        if (board_codes_playable(fw)) {
            ev = (uint32_t)((int32_t)DAC_MID + fw->out_code[0]);
            mv = (uint32_t)((int32_t)DAC_MID + fw->out_code[1]);
        }
#else
        uint32_t ev = to_code(0, v[0]), mv = to_code(1, v[1]);
#endif
        dma_buf[next_sample % BUF_SAMPLES] = (mv << 16) | ev;
        last_v[0] = v[0];
        last_v[1] = v[1];
        next_sample++;
    }
    fw_refill_end(fw); /* the refill's work, measured before the loop may sleep */
}

bool output_active(const fw_t *fw)
{
    return fw->playing || fw->amp_uv[0] > 0 || fw->amp_uv[1] > 0;
}

void output_emergency_zero(void)
{
    TIM6_CR1 = 0;      /* no more conversions from the buffer */
    DMA1_S5CR &= ~1u;
    DAC_CR &= ~((1u << 2) | (1u << 18)); /* software writes take effect at once */
    DAC_DHR12RD = MID_WORD;
}

void board_outputs_zero(void)
{
    /* Overwrite everything queued, so the zero is immediate, not after the render lead. */
    for (uint32_t i = 0; i < BUF_SAMPLES; i++) {
        dma_buf[i] = MID_WORD;
    }
    last_v[0] = last_v[1] = 0.0f;
}

void board_dac_last(float out[2])
{
    out[0] = last_v[0];
    out[1] = last_v[1];
}

void hw_watchdog_init(void)
{
    IWDG_KR = 0xCCCCu; /* start (LSI on); cannot be stopped */
    IWDG_KR = 0x5555u; /* unlock PR/RLR */
    IWDG_PR = 3u;      /* LSI / 32: 1 kHz at the nominal 32 kHz */
    IWDG_RLR = 100u;   /* 100 ms nominal, 68-188 ms over the LSI's 17-47 kHz */
    for (uint32_t i = 0; i < 100000u && IWDG_SR != 0u; i++) {
        /* PVU/RVU: the LSI domain takes a few of its cycles to see the new values */
    }
    IWDG_KR = 0xAAAAu;
}

void board_iwdg_feed(void)
{
    IWDG_KR = 0xAAAAu;
}

static debounce_t interlock;

static bool interlock_raw_open(void)
{
    /* The interlock chain pulls PC8 to ground when closed; anything else is open. */
    return (GPIO_IDR(GPIOC_BASE) & (1u << 8)) != 0;
}

void interlock_init(void)
{
    rcc_enable(&RCC_AHB1ENR, 1u << 2); /* GPIOC: errata-safe before the first access */
    GPIO_MODER(GPIOC_BASE) &= ~(3u << 16);                                        /* input */
    GPIO_PUPDR(GPIOC_BASE) = (GPIO_PUPDR(GPIOC_BASE) & ~(3u << 16)) | (1u << 16); /* pull-up */
    uint32_t t0 = board_micros32();
    debounce_init(&interlock, true, t0); /* open until the input has been closed for 5 ms */
    while ((uint32_t)(board_micros32() - t0) < 4u * INTERLOCK_DEBOUNCE_US) {
        (void)interlock_read_open(); /* a chain closed at power-up reports closed in BOOT */
    }
}

bool interlock_read_open(void)
{
    return debounce_step(&interlock, interlock_raw_open(), board_micros32(),
                         INTERLOCK_DEBOUNCE_US, INTERLOCK_DEBOUNCE_SAMPLES);
}

/* Attenuator control lines (docs/hardware.md): EV line A = PB5 (D4), B = PB4 (D5);
 * MV line A = PB10 (D6), B = PA8 (D7). Push-pull outputs, driven only when the board has more
 * than one step. */
static const struct {
    uint32_t port;
    uint32_t pin;
} att_pins[2][2] = {{{GPIOB_BASE, 5u}, {GPIOB_BASE, 4u}}, {{GPIOB_BASE, 10u}, {GPIOA_BASE, 8u}}};
static uint8_t att_steps[ATT_MAX_STEPS];
static unsigned att_count;

static unsigned att_lines(void)
{
    return att_count > 2u ? 2u : (att_count > 1u ? 1u : 0u);
}

void attenuator_init(void)
{
    att_count = att_parse(ATT_STEPS_DB, att_steps);
    if (att_lines() == 0u) {
        return;
    }
    rcc_enable(&RCC_AHB1ENR, 1u | (1u << 1)); /* GPIOA, GPIOB */
    for (int ch = 0; ch < 2; ch++) {
        for (unsigned line = 0; line < att_lines(); line++) {
            uint32_t port = att_pins[ch][line].port, pin = att_pins[ch][line].pin;
            GPIO_BSRR(port) = 1u << (pin + 16u); /* low first: the largest attenuation */
            GPIO_OTYPER(port) &= ~(1u << pin);
            GPIO_MODER(port) = (GPIO_MODER(port) & ~(3u << (2u * pin))) | (1u << (2u * pin));
        }
    }
}

void board_set_attenuator(int ch, uint8_t step_index)
{
    if (ch < 0 || ch > 1 || step_index >= att_count) {
        return; /* the core validates steps against HELLO att; nothing to switch */
    }
    uint32_t code = att_line_code(step_index, att_count);
    for (unsigned line = 0; line < att_lines(); line++) {
        uint32_t port = att_pins[ch][line].port, pin = att_pins[ch][line].pin;
        GPIO_BSRR(port) = (code >> line) & 1u ? 1u << pin : 1u << (pin + 16u);
    }
}
