/* Real board outputs: DAC1 (PA4) = EV, DAC2 (PA5) = MV, both converted on every TIM6 update
 * (20 kHz) from one circular DMA buffer of dual-channel words (DHR12RD), refilled from the
 * main loop a few ms ahead of the DMA read position. Mid-scale (2048) is 0 V drive: the
 * input stage subtracts the 1.65 V reference (docs/hardware.md). Also the IWDG and the
 * interlock input (PC8, pull-up: an open loop or a broken wire reads as open). */
#include <math.h>

#include "../core/board.h"
#include "regs.h"
#include "stm32.h"

#define BUF_SAMPLES 512u         /* 25.6 ms at 20 kHz */
#define LEAD_SAMPLES 200u        /* keep ~10 ms rendered ahead of the DMA */
#define DAC_FULL_SCALE_V 10.0f   /* drive at full DAC swing after the input stage */
#define MID 2048u
#define MID_WORD ((MID << 16) | MID)

static volatile uint32_t dma_buf[BUF_SAMPLES];
static uint64_t next_sample;     /* absolute index of the next sample to render */
static uint64_t dma_start_us;    /* device time of sample 0 */
static uint32_t last_pos;
static uint64_t wraps;
static float last_v[2];

static uint32_t to_code(float v)
{
    float c = (float)MID + v / DAC_FULL_SCALE_V * 2047.0f;
    if (c < 0.0f) {
        c = 0.0f;
    } else if (c > 4095.0f) {
        c = 4095.0f;
    }
    return (uint32_t)lrintf(c);
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
    RCC_AHB1ENR |= 1u | (1u << 21);      /* GPIOA, DMA1 */
    RCC_APB1ENR |= (1u << 29) | (1u << 4); /* DAC, TIM6 */
    GPIO_MODER(GPIOA_BASE) |= (3u << 8) | (3u << 10); /* PA4, PA5 analog */
    TIM6_CR1 = 0;
    DMA1_S5CR = 0;
    while (DMA1_S5CR & 1u) {
    }
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
        dma_buf[next_sample % BUF_SAMPLES] = (to_code(v[1]) << 16) | to_code(v[0]);
        last_v[0] = v[0];
        last_v[1] = v[1];
        next_sample++;
    }
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
    IWDG_KR = 0x5555u; /* unlock PR/RLR */
    IWDG_PR = 3u;      /* LSI 32 kHz / 32 = 1 kHz */
    IWDG_RLR = 100u;   /* 100 ms: a hung main loop resets the MCU, DACs off */
    IWDG_KR = 0xCCCCu; /* start; cannot be stopped */
}

void hw_watchdog_feed(void)
{
    IWDG_KR = 0xAAAAu;
}

void interlock_init(void)
{
    RCC_AHB1ENR |= (1u << 2); /* GPIOC */
    GPIO_MODER(GPIOC_BASE) &= ~(3u << 16);                                /* PC8 input */
    GPIO_PUPDR(GPIOC_BASE) = (GPIO_PUPDR(GPIOC_BASE) & ~(3u << 16)) | (1u << 16); /* pull-up */
}

bool interlock_read_open(void)
{
    /* The interlock chain pulls PC8 to ground when closed; anything else is open. */
    return (GPIO_IDR(GPIOC_BASE) & (1u << 8)) != 0;
}
