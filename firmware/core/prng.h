/* The virtual-time onset lateness generator, shared bit for bit with the Python emulator
 * (masking_lab/device/emulator_state.py, OnsetLateness) so that a whole simulated session
 * gives the same trial records on either implementation. Documented in
 * docs/device-protocol.md, "Virtual time". */
#ifndef ML_PRNG_H
#define ML_PRNG_H

#include <stdint.h>

#define PRNG_SEED_MIX 0x6D2B79F5u

typedef struct {
    uint32_t state;
} prng_t;

/* state = (seed mod 2^32) xor 0x6D2B79F5, or 0x6D2B79F5 if that is 0 (xorshift needs != 0). */
void prng_seed(prng_t *p, uint32_t seed);

/* Marsaglia xorshift32 (13, 17, 5). */
uint32_t prng_next(prng_t *p);

/* Lateness of one onset, µs: next() mod (max_us + 1). */
uint32_t prng_lateness_us(prng_t *p, uint32_t max_us);

#endif
