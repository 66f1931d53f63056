/* The device clock: board_micros32() extended to 64 bits, and saturating differences.
 *
 * The 32-bit counter wraps every 2^32 µs (71.6 min); any call within that span of the last
 * one sees at most one wrap, which shows as a much smaller raw value (back by more than
 * 2^31 µs). The core polls it at least every millisecond, so no wrap is missed; a small
 * step back (a counter read glitch) holds the clock instead of moving it back. */
#include "clock.h"

#include "board.h"

static uint32_t last_raw;
static uint64_t high; /* wraps seen, times 2^32 */

uint64_t clock_now_us(void)
{
    uint32_t raw = board_micros32();
    if (raw < last_raw) {
        if (last_raw - raw > 0x80000000u) {
            high += (uint64_t)1 << 32; /* a wrap: from near 2^32 to near 0 */
        } else {
            raw = last_raw; /* a counter that stepped back a little: hold, never go back */
        }
    }
    last_raw = raw;
    return high + raw;
}

uint64_t clock_since_us(uint64_t now, uint64_t then)
{
    return now > then ? now - then : 0;
}

int64_t clock_add_sat(int64_t a, int64_t b)
{
    if (b > 0 && a > INT64_MAX - b) {
        return INT64_MAX;
    }
    if (b < 0 && a < INT64_MIN - b) {
        return INT64_MIN;
    }
    return a + b;
}

/* Weak defaults so a board layer that still provides only board_mono_us() (or none of the v2
 * additions) links; a board's own definitions replace them. */
__attribute__((weak)) uint64_t board_mono_us(void)
{
    return clock_now_us();
}

__attribute__((weak)) uint32_t board_micros32(void)
{
    return (uint32_t)board_mono_us();
}

__attribute__((weak)) const char *board_reset_cause(void)
{
    return "unknown";
}

__attribute__((weak)) const char *board_clock_source(void)
{
    return "hsi";
}

__attribute__((weak)) void board_set_attenuator(int ch, uint8_t step_index)
{
    (void)ch;
    (void)step_index;
}

__attribute__((weak)) void board_iwdg_feed(void)
{
}
