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
#define TIM2_CLOCK_HZ 84000000u /* APB1 42 MHz, prescaler != 1: timers run at 2 x PCLK1 */
#define BOARD_IRQS 97           /* RM0390 vector table: positions 0..96 (FMPI2C1 error last) */
#define BOARD_MODEL "ML-FW-2CH" /* HELLO model; fw is the plain FW_VERSION */
#elif defined(BOARD_QEMU_NETDUINOPLUS2)
#define HOST_USART_BASE USART1_BASE /* QEMU maps serial0 to USART1 */
#define HOST_USART_IRQ IRQ_USART1
#define HOST_USART_PCLK 84000000u
#define TIM2_CLOCK_HZ 1000000000u /* QEMU's stm32f405 clocks TIM2-5 at 1 GHz */
#define BOARD_IRQS 82             /* RM0090: positions 0..81 (FPU last) */
#define BOARD_MODEL "ML-FW-2CH-QEMU"
#else
#error "define BOARD_NUCLEO_F446RE or BOARD_QEMU_NETDUINOPLUS2"
#endif

#define CORE_CLOCK_HZ 168000000u
#define HOST_BAUD 115200u

void HardFault_Handler(void);

void reset_cause_capture(void);   /* read and clear RCC_CSR: first thing in main() */
void clock_init(void);            /* HSE/HSI -> PLL 168 MHz (real board), TIM2 1 MHz, SysTick */

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
/* v2 core: false (and the core's LIMIT fault raised, outputs zeroed) when a rendered code lies
 * outside the DAC buffer's linear range. */
bool board_codes_playable(fw_t *fw);
void interlock_init(void);        /* needs clock_init(): debounced on board_micros32() */
bool interlock_read_open(void);   /* true = open: HV enable off, E-stop hit, wristband off */
void attenuator_init(void);       /* control lines out, at the largest attenuation */
void hw_watchdog_init(void);      /* IWDG (QEMU: a feed counter) */

/* Interlock debounce: a change is taken after >= 5 equal samples spanning >= 5 ms. */
#define INTERLOCK_DEBOUNCE_US 5000u
#define INTERLOCK_DEBOUNCE_SAMPLES 5u

/* Rig options (Makefile variables; defaults for a bare build). */
#ifndef LIMIT_EV_UV
#define LIMIT_EV_UV 5000000LL
#endif
#ifndef LIMIT_MV_UV
#define LIMIT_MV_UV 8700000LL /* inside the linear range of a 10 V stage (8.779 V) */
#endif
#ifndef WATCHDOG_MS
#define WATCHDOG_MS 500u
#endif
#ifndef SERIAL_NUMBER
#define SERIAL_NUMBER "ML-0001"
#endif
#ifndef FSV_EV_UV
#define FSV_EV_UV 10000000LL
#endif
#ifndef FSV_MV_UV
#define FSV_MV_UV 10000000LL
#endif
#ifndef ATT_STEPS_DB
#define ATT_STEPS_DB "0"
#endif
#ifndef FW_BUILD
#define FW_BUILD "000000000000"
#endif
#define DAC_BITS 12

#endif
