#include "prng.h"

void prng_seed(prng_t *p, uint32_t seed)
{
    uint32_t s = seed ^ PRNG_SEED_MIX;
    p->state = s ? s : PRNG_SEED_MIX;
}

uint32_t prng_next(prng_t *p)
{
    uint32_t x = p->state;
    x ^= x << 13;
    x ^= x >> 17;
    x ^= x << 5;
    p->state = x;
    return x;
}

uint32_t prng_lateness_us(prng_t *p, uint32_t max_us)
{
    uint32_t r = prng_next(p);
    return max_us == UINT32_MAX ? r : r % (max_us + 1u);
}
