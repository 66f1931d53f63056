/* What the portable core needs from a board. Each board layer (host, stm32, qemu) implements
 * these; nothing else in core/ touches hardware. */
#ifndef ML_BOARD_H
#define ML_BOARD_H

#include <stddef.h>
#include <stdint.h>

/* Free-running 32-bit microsecond counter (STM32: TIM2/TIM5 at 1 MHz). It never steps back;
 * it wraps every 71.6 minutes, which the core detects (core/clock.c). */
uint32_t board_micros32(void);

/* Monotonic µs since boot: a derived helper implemented in the core (core/clock.c) from
 * board_micros32(); boards may call it. */
uint64_t board_mono_us(void);

/* Reset cause of this boot: "pin", "watchdog", "brownout", "software", "power", "unknown". */
const char *board_reset_cause(void);

/* System clock source: "hse", "hsi" (flagged fallback) or "host". */
const char *board_clock_source(void);

/* Switch channel ch's attenuator to step `step_index` of the board's list (no-op if none). */
void board_set_attenuator(int ch, uint8_t step_index);

/* Feed the independent watchdog (host build: the modelled IWDG). */
void board_iwdg_feed(void);

/* Queue bytes for the host link. Must not block for long: drop if the link is full. */
void board_tx(const char *data, size_t len);

/* Silence both outputs *now*: drop any samples already queued for the DAC and drive 0 V.
 * Called on every zeroing (STOP, ERR, FAULT, WATCHDOG, HELLO, interlock open). */
void board_outputs_zero(void);

/* Last value written to each DAC channel, V at the amplifier input (for DIAG). */
void board_dac_last(float out[2]);

/* Protocol v2 board functions (PROTOCOL-V2.md). */
uint32_t board_micros32(void);
const char *board_reset_cause(void);
const char *board_clock_source(void);
void board_set_attenuator(int ch, uint8_t step_index);
void board_iwdg_feed(void);

#endif
