/* The STM32 board layer's internal interface (startup, clock, USART, output back-ends). */
#ifndef ML_STM32_H
#define ML_STM32_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "../core/fw.h"

/* Board selection: BOARD_NUCLEO_F446RE (real DACs, IWDG, interlock GPIO) or
 * BOARD_QEMU_NETDUINOPLUS2 (QEMU's STM32F405: no RCC, DAC, DMA, GPIO or IWDG models). */
#if defined(BOARD_NUCLEO_F446RE)
#define HOST_USART_BASE USART2_BASE /* ST-Link virtual COM port, PA2/PA3 */
#define HOST_USART_IRQ IRQ_USART2
#define HOST_USART_PCLK 42000000u
#define BOARD_FW_SUFFIX "+stm32"
#elif defined(BOARD_QEMU_NETDUINOPLUS2)
#define HOST_USART_BASE USART1_BASE /* QEMU maps serial0 to USART1 */
#define HOST_USART_IRQ IRQ_USART1
#define HOST_USART_PCLK 84000000u
#define BOARD_FW_SUFFIX "+qemu"
#else
#error "define BOARD_NUCLEO_F446RE or BOARD_QEMU_NETDUINOPLUS2"
#endif

#define CORE_CLOCK_HZ 168000000u
#define HOST_BAUD 115200u

void HardFault_Handler(void);

void clock_init(void);            /* PLL to 168 MHz (real board), SysTick at 1 kHz */

void usart_init(void);            /* host link, RX interrupt into a ring buffer */
size_t usart_read(uint8_t *buf, size_t cap);
void usart_write(const char *data, size_t len);
void usart_pump(void);            /* move queued TX bytes into the data register */
bool usart_rx_pending(void);

/* Output back-end: output_dac.c (DMA-fed DACs) or output_ram.c (QEMU: RAM recorder). */
void output_init(fw_t *fw);
void output_service(fw_t *fw);    /* keep the sample stream fed from fw_render() */
void output_emergency_zero(void); /* from fault handlers: no core state, registers only */
bool output_active(const fw_t *fw);
void interlock_init(void);
bool interlock_read_open(void);   /* true = open: HV enable off, E-stop hit, wristband off */
void hw_watchdog_init(void);
void hw_watchdog_feed(void);

#endif
