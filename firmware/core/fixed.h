/* Decimal text <-> micro-units (µs, µV, µHz) as int64, so numbers cross the wire exactly.
 *
 * The protocol sends at most 6 decimals and never exponents; parsing into integers keeps
 * every time and amplitude exact, so the firmware and the Python emulator (which also counts
 * virtual time in integer µs) print byte-identical DONE lines. */
#ifndef ML_FIXED_H
#define ML_FIXED_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#define FX_ONE 1000000LL /* one unit (s, V, Hz) in micro-units */

/* Parse "[-+]digits[.digits]" into micro-units, rounding half away from zero beyond 6
 * decimals. False for empty text, exponents, nan/inf, other characters or > 12 integer
 * digits. */
bool fx_parse(const char *text, int64_t *out);

/* Format micro-units like masking_lab.device.protocol.fmt_number: up to 6 decimals, trailing
 * zeros and a bare '.' stripped, "-0" printed as "0". Returns the length written (NUL added). */
size_t fx_format(char *buf, size_t cap, int64_t micro);

#endif
