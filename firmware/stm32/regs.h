/* Minimal STM32F4 register definitions: only what this firmware touches, by address, from
 * the STM32F4 reference manual (RM0390 for F446, RM0090 for F405). No vendor headers. */
#ifndef ML_REGS_H
#define ML_REGS_H

#include <stdint.h>

#define REG32(addr) (*(volatile uint32_t *)(uintptr_t)(addr))

/* Cortex-M4 system control */
#define SCB_CPACR REG32(0xE000ED88u) /* coprocessor access: CP10/CP11 = FPU */
#define SCB_VTOR REG32(0xE000ED08u)
#define SCB_SHCSR REG32(0xE000ED24u) /* enable MemManage/BusFault/UsageFault handlers */
#define SYST_CSR REG32(0xE000E010u)
#define SYST_RVR REG32(0xE000E014u)
#define SYST_CVR REG32(0xE000E018u)
#define NVIC_ISER(n) REG32(0xE000E100u + 4u * (n))

/* RCC */
#define RCC_BASE 0x40023800u
#define RCC_CR REG32(RCC_BASE + 0x00u)
#define RCC_PLLCFGR REG32(RCC_BASE + 0x04u)
#define RCC_CFGR REG32(RCC_BASE + 0x08u)
#define RCC_AHB1ENR REG32(RCC_BASE + 0x30u)
#define RCC_APB1ENR REG32(RCC_BASE + 0x40u)
#define RCC_APB2ENR REG32(RCC_BASE + 0x44u)
#define RCC_CSR REG32(RCC_BASE + 0x74u)
#define RCC_CR_HSEON (1u << 16)
#define RCC_CR_HSERDY (1u << 17)
#define RCC_CR_HSEBYP (1u << 18)
#define RCC_CR_CSSON (1u << 19)
#define RCC_CR_PLLON (1u << 24)
#define RCC_CR_PLLRDY (1u << 25)
#define FLASH_ACR REG32(0x40023C00u)
#define PWR_CR REG32(0x40007000u)
#define PWR_CSR REG32(0x40007004u)
#define PWR_CSR_VOSRDY (1u << 14) /* RM0390 PWR_CSR bit 14 (ST CMSIS stm32f446xx.h: _Pos 14U) */

/* GPIO */
#define GPIOA_BASE 0x40020000u
#define GPIOB_BASE 0x40020400u
#define GPIOC_BASE 0x40020800u
#define GPIO_MODER(b) REG32((b) + 0x00u)
#define GPIO_OTYPER(b) REG32((b) + 0x04u)
#define GPIO_PUPDR(b) REG32((b) + 0x0Cu)
#define GPIO_IDR(b) REG32((b) + 0x10u)
#define GPIO_BSRR(b) REG32((b) + 0x18u)
#define GPIO_AFRL(b) REG32((b) + 0x20u)
#define GPIO_AFRH(b) REG32((b) + 0x24u)

/* USART (same layout on every STM32F4 USART) */
#define USART1_BASE 0x40011000u
#define USART2_BASE 0x40004400u
#define USART_SR(b) REG32((b) + 0x00u)
#define USART_DR(b) REG32((b) + 0x04u)
#define USART_BRR(b) REG32((b) + 0x08u)
#define USART_CR1(b) REG32((b) + 0x0Cu)
#define USART_SR_RXNE (1u << 5)
#define USART_SR_TXE (1u << 7)
#define USART_SR_ORE (1u << 3)
#define USART_CR1_UE (1u << 13)
#define USART_CR1_TXEIE (1u << 7)
#define USART_CR1_RXNEIE (1u << 5)
#define USART_CR1_TE (1u << 3)
#define USART_CR1_RE (1u << 2)
#define IRQ_USART1 37
#define IRQ_USART2 38

/* DAC (two 12-bit channels), TIM6 (its trigger), DMA1 stream 5 (DAC1 request, channel 7) */
#define DAC_BASE 0x40007400u
#define DAC_CR REG32(DAC_BASE + 0x00u)
#define DAC_DHR12RD REG32(DAC_BASE + 0x20u) /* both channels in one word: ch2 in bits 27:16 */
#define TIM6_BASE 0x40001000u
#define TIM6_CR1 REG32(TIM6_BASE + 0x00u)
#define TIM6_CR2 REG32(TIM6_BASE + 0x04u)
#define TIM6_PSC REG32(TIM6_BASE + 0x28u)
#define TIM6_ARR REG32(TIM6_BASE + 0x2Cu)
#define DMA1_BASE 0x40026000u
#define DMA1_LIFCR REG32(DMA1_BASE + 0x08u)
#define DMA1_HIFCR REG32(DMA1_BASE + 0x0Cu)
#define DMA1_S5CR REG32(DMA1_BASE + 0x10u + 0x18u * 5u)
#define DMA1_S5NDTR REG32(DMA1_BASE + 0x14u + 0x18u * 5u)
#define DMA1_S5PAR REG32(DMA1_BASE + 0x18u + 0x18u * 5u)
#define DMA1_S5M0AR REG32(DMA1_BASE + 0x1Cu + 0x18u * 5u)

/* TIM2: 32-bit general-purpose timer, the device's free-running microsecond clock. QEMU's
 * netduinoplus2 models TIM2-5 (hw/timer/stm32f2xx_timer.c) with a 1 GHz input clock. */
#define TIM2_BASE 0x40000000u
#define TIM2_CR1 REG32(TIM2_BASE + 0x00u)
#define TIM2_SR REG32(TIM2_BASE + 0x10u)
#define TIM2_EGR REG32(TIM2_BASE + 0x14u)
#define TIM2_CNT REG32(TIM2_BASE + 0x24u)
#define TIM2_PSC REG32(TIM2_BASE + 0x28u)
#define TIM2_ARR REG32(TIM2_BASE + 0x2Cu)

/* Independent watchdog (LSI, 32 kHz nominal, 17-47 kHz over the F446's range) */
#define IWDG_KR REG32(0x40003000u)
#define IWDG_PR REG32(0x40003004u)
#define IWDG_RLR REG32(0x40003008u)
#define IWDG_SR REG32(0x4000300Cu)

static inline void irq_disable(void) { __asm__ volatile("cpsid i" ::: "memory"); }
static inline void irq_enable(void) { __asm__ volatile("cpsie i" ::: "memory"); }
static inline void wait_for_interrupt(void) { __asm__ volatile("wfi"); }
static inline void data_sync_barrier(void) { __asm__ volatile("dsb" ::: "memory"); }

/* Enable a peripheral clock and wait until it reaches the peripheral: the F446 errata sheet
 * (ES0298, "Delay after an RCC peripheral clock enabling") asks for 2 AHB cycles (AHB) or
 * 1 + AHB/APB prescaler cycles (APB) before the first access; reading the enable register back
 * and a DSB cover both. */
static inline void rcc_enable(volatile uint32_t *enr, uint32_t bits)
{
    *enr |= bits;
    (void)*enr;
    data_sync_barrier();
}

#endif
