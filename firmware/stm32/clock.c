/* System clock, the device's microsecond clock (TIM2) and the reset cause.
 *
 * Nucleo-F446RE: HSE in bypass mode from the ST-Link's 8 MHz MCO on OSC_IN (PH0); if it does
 * not start, HSI 16 MHz is the fallback and HELLO says `clk=hsi`. Either way the PLL input is
 * 2 MHz and SYSCLK 168 MHz (scale 1 needs no over-drive up to 168 MHz), and the voltage scale,
 * flash wait states, PLL and clock switch are read back: a setting that did not take halts the
 * board before anything is enabled (DACs off = 0 V drive). QEMU's netduinoplus2 has no RCC
 * model (its registers read 0): the same HSE probe times out, so the QEMU image reports `hsi`,
 * and the PLL is left alone (QEMU's CPU clock is fixed at 168 MHz). */
#include "../core/board.h"
#include "board_logic.h"
#include "regs.h"
#include "stm32.h"

volatile uint32_t systick_ticks; /* 1 kHz: wakes the main loop from WFI; not the clock */
volatile uint32_t reset_csr_raw; /* RCC_CSR as found at boot (gdb / QEMU monitor) */
const char *board_clock_word = "hsi"; /* exported for gdb / the QEMU monitor */
const char *board_reset_word = "unknown";

void SysTick_Handler(void)
{
    systick_ticks++;
}

void reset_cause_capture(void)
{
    reset_csr_raw = RCC_CSR;
    board_reset_word = reset_cause_word(reset_csr_raw);
    RCC_CSR |= RCC_CSR_RMVF; /* clear the flags: the next boot reports only its own cause */
}

const char *board_reset_cause(void)
{
    return board_reset_word;
}

const char *board_clock_source(void)
{
    return board_clock_word;
}

/* ~10-20 ms at 16 MHz HSI: an external clock is ready within a few HSE cycles. */
#define HSE_TIMEOUT_LOOPS 40000u
#define PLL_TIMEOUT_LOOPS 200000u

static bool wait_set(volatile uint32_t *reg, uint32_t mask, uint32_t want, uint32_t loops)
{
    for (uint32_t i = 0; i < loops; i++) {
        if ((*reg & mask) == want) {
            return true;
        }
    }
    return false;
}

static bool hse_bypass_start(void)
{
    RCC_CR |= RCC_CR_HSEBYP; /* an external clock, not a crystal: set before HSEON */
    RCC_CR |= RCC_CR_HSEON;
    if (wait_set(&RCC_CR, RCC_CR_HSERDY, RCC_CR_HSERDY, HSE_TIMEOUT_LOOPS)) {
        return true;
    }
    RCC_CR &= ~RCC_CR_HSEON;
    RCC_CR &= ~RCC_CR_HSEBYP; /* writable only with HSE off */
    return false;
}

#if defined(BOARD_NUCLEO_F446RE)
static void __attribute__((noreturn)) clock_fault(void)
{
    /* Nothing is enabled yet (DACs, timers and the IWDG are in their reset state): halting
     * here keeps both outputs at 0 V; the host sees no BOOT and no HELLO answer. */
    irq_disable();
    for (;;) {
    }
}

#define FLASH_ACR_5WS ((1u << 8) | (1u << 9) | (1u << 10) | 5u) /* prefetch, I/D cache */
#define CFGR_168MHZ ((5u << 10) | (4u << 13) | 2u) /* APB1 /4 = 42, APB2 /2 = 84, SW = PLL */

static bool pll_168mhz(bool hse)
{
    rcc_enable(&RCC_APB1ENR, 1u << 28); /* PWR */
    PWR_CR = (PWR_CR & ~(3u << 14)) | (3u << 14); /* VOS = scale 1 (writable with PLL off) */
    FLASH_ACR = FLASH_ACR_5WS; /* 150 < HCLK <= 180 MHz at 2.7-3.6 V: 5 wait states */
    if ((FLASH_ACR & 0xFu) != 5u) {
        return false; /* RM0390, flash read latency: check it took before raising the clock */
    }
    uint32_t cfgr = pll_cfgr_168mhz(hse ? 8000000u : 16000000u, hse);
    RCC_PLLCFGR = cfgr;
    if (RCC_PLLCFGR != cfgr) {
        return false;
    }
    RCC_CR |= RCC_CR_PLLON;
    if (!wait_set(&RCC_CR, RCC_CR_PLLRDY, RCC_CR_PLLRDY, PLL_TIMEOUT_LOOPS)) {
        return false;
    }
    /* the scale takes effect with the PLL on: wait for it, then check it is scale 1 */
    if (!wait_set(&PWR_CSR, PWR_CSR_VOSRDY, PWR_CSR_VOSRDY, PLL_TIMEOUT_LOOPS) ||
        ((PWR_CR >> 14) & 3u) != 3u) {
        return false;
    }
    RCC_CFGR = CFGR_168MHZ & ~3u; /* bus prescalers first, so no bus ever runs too fast */
    RCC_CFGR = CFGR_168MHZ;
    return wait_set(&RCC_CFGR, 3u << 2, 2u << 2, PLL_TIMEOUT_LOOPS) && /* SWS = PLL */
           (RCC_CFGR & ~(3u << 2)) == CFGR_168MHZ; /* SWS is read-only status */
}
#endif

static void micros_init(void)
{
    rcc_enable(&RCC_APB1ENR, 1u << 0); /* TIM2 */
    TIM2_CR1 = 0;
    TIM2_PSC = TIM2_CLOCK_HZ / 1000000u - 1u; /* 1 MHz */
    TIM2_ARR = 0xFFFFFFFFu;                   /* free-running over all 32 bits */
    TIM2_EGR = 1u;                            /* UG: the prescaler is buffered; load it now */
    TIM2_SR = 0;
    TIM2_CNT = 0;
    TIM2_CR1 = 1u; /* CEN, up-counting, no interrupt */
}

void clock_init(void)
{
    bool hse = hse_bypass_start();
    board_clock_word = hse ? "hse" : "hsi";
#if defined(BOARD_NUCLEO_F446RE)
    if (!pll_168mhz(hse)) {
        clock_fault();
    }
    if (hse) {
        RCC_CR |= RCC_CR_CSSON; /* HSE lost: NMI (outputs zeroed, IWDG reset, HSI next boot) */
    }
#endif
    micros_init();
    SYST_RVR = CORE_CLOCK_HZ / 1000u - 1u;
    SYST_CVR = 0;
    SYST_CSR = 7u; /* processor clock, interrupt, enable */
}

uint32_t board_micros32(void)
{
    return TIM2_CNT;
}

/* 64-bit extension of board_micros32(), main-loop context only (called far more often than
 * the 71-minute wrap). Weak: the core's own derived helper replaces it where it has one. */
__attribute__((weak)) uint64_t board_mono_us(void)
{
    static uint32_t last;
    static uint64_t high;
    uint32_t now = board_micros32();
    if (now < last) {
        high += 1ull << 32;
    }
    last = now;
    return high | now;
}
