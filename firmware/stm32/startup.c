/* Reset handler and vector table. The FPU is switched on first: the core, built with
 * -mfloat-abi=hard, may use FP registers in any function after this one. */
#include <stdint.h>

#include "regs.h"
#include "stm32.h"

extern uint32_t _sidata, _sdata, _edata, _sbss, _ebss, _estack;
int main(void);
void Reset_Handler(void);
void Default_Handler(void);
void HardFault_Handler(void);
void MemManage_Handler(void);
void BusFault_Handler(void);
void UsageFault_Handler(void);
void NMI_Handler(void);
void SysTick_Handler(void);
void USART1_IRQHandler(void);
void USART2_IRQHandler(void);

__attribute__((used, noreturn)) void Reset_Handler(void)
{
    SCB_CPACR |= (0xFu << 20); /* CP10 + CP11 full access */
    __asm__ volatile("dsb\n isb" ::: "memory");
    const uint32_t *src = &_sidata;
    for (uint32_t *dst = &_sdata; dst < &_edata;) {
        *dst++ = *src++;
    }
    for (uint32_t *dst = &_sbss; dst < &_ebss;) {
        *dst++ = 0;
    }
    /* trap faults in their own handlers (which zero the DACs) rather than escalating */
    SCB_SHCSR |= (1u << 16) | (1u << 17) | (1u << 18);
    main();
    for (;;) {
    }
}

void Default_Handler(void)
{
    HardFault_Handler(); /* an unexpected interrupt is a bug: treat it as a fault */
}

/* Every position the reference manual lists (F446: 16 system + 97 IRQs), each with a handler:
 * an interrupt nobody expects lands in Default_Handler (a fault: outputs zeroed), never at a
 * null vector. */
#define VECTORS (16 + BOARD_IRQS)

#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Woverride-init" /* the range default, then named entries */
__attribute__((section(".isr_vector"), used)) void (*const vector_table[VECTORS])(void) = {
    [1 ... VECTORS - 1] = Default_Handler,
    [0] = (void (*)(void))(&_estack),
    [1] = Reset_Handler,
    [2] = NMI_Handler,
    [3] = HardFault_Handler,
    [4] = MemManage_Handler,
    [5] = BusFault_Handler,
    [6] = UsageFault_Handler,
    [15] = SysTick_Handler,
    [16 + IRQ_USART1] = USART1_IRQHandler,
    [16 + IRQ_USART2] = USART2_IRQHandler,
};
#pragma GCC diagnostic pop
