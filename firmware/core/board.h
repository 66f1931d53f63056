/* What the portable core needs from a board. Each board layer (host, stm32, qemu) implements
 * these; nothing else in core/ touches hardware. */
#ifndef ML_BOARD_H
#define ML_BOARD_H

#include <stddef.h>
#include <stdint.h>

/* Monotonic time since boot, µs. The device clock in real time, and always the watchdog's. */
uint64_t board_mono_us(void);

/* Queue bytes for the host link. Must not block for long: drop if the link is full. */
void board_tx(const char *data, size_t len);

/* Silence both outputs *now*: drop any samples already queued for the DAC and drive 0 V.
 * Called on every zeroing (STOP, ERR, FAULT, WATCHDOG, HELLO, interlock open). */
void board_outputs_zero(void);

/* Last value written to each DAC channel, V (for DIAG). */
void board_dac_last(float out[2]);

/* Protocol v2 board functions (PROTOCOL-V2.md). */
uint32_t board_micros32(void);
const char *board_reset_cause(void);
const char *board_clock_source(void);
void board_set_attenuator(int ch, uint8_t step_index);
void board_iwdg_feed(void);

#endif
