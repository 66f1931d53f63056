/* Core clock and the device's microsecond clock (SysTick, 1 kHz interrupt + counter). */
#include "../core/board.h"
#include "regs.h"
#include "stm32.h"

static volatile uint64_t systick_ms;

void SysTick_Handler(void)
{
    systick_ms++;
}

#if defined(BOARD_NUCLEO_F446RE)
/* HSI 16 MHz -> PLL: /16 *336 /2 = 168 MHz; APB1 /4 = 42 MHz, APB2 /2 = 84 MHz. 168 MHz needs
 * no over-drive on the F446 and divides evenly into the 20 kHz DAC trigger of TIM6. */
static void pll_168mhz(void)
{
    RCC_APB1ENR |= (1u << 28); /* PWR */
    PWR_CR |= (3u << 14);      /* voltage scale 1 */
    FLASH_ACR = (1u << 8) | (1u << 9) | (1u << 10) | 5u; /* prefetch, I/D cache, 5 WS */
    RCC_PLLCFGR = 16u | (336u << 6) | (0u << 16) | (0u << 22) | (7u << 24); /* HSI source */
    RCC_CR |= (1u << 24);      /* PLLON */
    while (!(RCC_CR & (1u << 25))) {
    }
    RCC_CFGR = (5u << 10) | (4u << 13) | 2u; /* APB1 /4, APB2 /2, SYSCLK = PLL */
    while (((RCC_CFGR >> 2) & 3u) != 2u) {
    }
}
#endif

void clock_init(void)
{
#if defined(BOARD_NUCLEO_F446RE)
    pll_168mhz();
#endif
    /* QEMU's netduinoplus2 runs its CPU clock at 168 MHz and has no RCC model: nothing to do */
    SYST_RVR = CORE_CLOCK_HZ / 1000u - 1u;
    SYST_CVR = 0;
    SYST_CSR = 7u; /* processor clock, interrupt, enable */
}

uint64_t board_mono_us(void)
{
    uint64_t ms1, ms2;
    uint32_t val;
    do {
        ms1 = systick_ms;
        val = SYST_CVR;
        ms2 = systick_ms;
    } while (ms1 != ms2);
    uint32_t load = SYST_RVR + 1u;
    return ms1 * 1000u + (uint64_t)(load - 1u - val) * 1000u / load;
}
