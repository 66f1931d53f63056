/* Device clock helpers: 64-bit monotonic µs from the board's 32-bit counter, saturating. */
#ifndef ML_CLOCK_H
#define ML_CLOCK_H

#include <stdint.h>

/* Monotonic µs since boot (board_micros32() with wrap detection). Never steps back. */
uint64_t clock_now_us(void);

/* now - then, or 0 if then is later: a difference that cannot wrap. */
uint64_t clock_since_us(uint64_t now, uint64_t then);

/* a + b saturated to the int64 range. */
int64_t clock_add_sat(int64_t a, int64_t b);

#endif
