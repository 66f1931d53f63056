/* Fault handlers: the first thing any fault does is silence both outputs, using registers
 * only (core state may be what is corrupt). Then the core stops; on the real board the
 * independent watchdog, no longer fed, resets the MCU, which reboots with the DACs off and
 * announces "BOOT" to the host. */
#include "regs.h"
#include "stm32.h"

static void __attribute__((noreturn)) fault_stop(void)
{
    irq_disable();
    output_emergency_zero();
    for (;;) {
        /* not feeding the IWDG: it resets us within its period */
    }
}

void HardFault_Handler(void) { fault_stop(); }
void MemManage_Handler(void) { fault_stop(); }
void BusFault_Handler(void) { fault_stop(); }
void UsageFault_Handler(void) { fault_stop(); }
void NMI_Handler(void) { fault_stop(); } /* clock security system or a parity error */
