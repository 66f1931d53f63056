#include "synth.h"

#include <math.h>

#define TWO_PI 6.28318530717958647692f
#define PI_F 3.14159265358979323846f

uint32_t us_to_samples(int64_t us, uint32_t fs_hz)
{
    if (us <= 0) {
        return 0;
    }
    /* us <= 2^63 / 2^32 keeps the product in range; beyond that saturate */
    if ((uint64_t)us > UINT64_MAX / 4294967296u) {
        return UINT32_MAX;
    }
    uint64_t s = ((uint64_t)us * fs_hz + 500000u) / 1000000u;
    return s > UINT32_MAX ? UINT32_MAX : (uint32_t)s;
}

/* (f * i) mod period without overflow: f < period < 2^40 (fs <= 1 MHz), i < 2^32. The
 * direct product fits below 2^63 while i < 2^23 (every trial up to fs = 140 kHz); beyond
 * that (long streams, high rates) i is split into 16-bit halves. */
static uint64_t mulmod(uint64_t f, uint32_t i, uint64_t period)
{
    if (i < (1u << 23)) {
        return f * i % period;
    }
    uint64_t hi = f * (i >> 16) % period;
    return ((hi << 16) % period + f * (i & 0xFFFFu) % period) % period;
}

/* fraction of a cycle of frequency f_uhz after i samples, in [0, 1) */
static float cycle_fraction(int64_t f_uhz, uint32_t i, uint32_t fs_hz)
{
    uint64_t period = (uint64_t)fs_hz * 1000000u;
    uint64_t f = (uint64_t)(f_uhz % (int64_t)period); /* f_uhz > 0: checked at the command */
    return (float)mulmod(f, i, period) / (float)period;
}

float tone_unit(const tone_t *t, uint32_t i)
{
    if (t->n && i >= t->n) {
        return 0.0f;
    }
    float w = 1.0f;
    if (i < t->ramp) {
        w = 0.5f * (1.0f - cosf(PI_F * (float)i / (float)t->ramp));
    } else if (t->n && i >= t->n - t->ramp) {
        uint32_t k = t->n - 1 - i; /* mirror of the rise */
        w = (i == t->n - 1) ? 0.0f : 0.5f * (1.0f - cosf(PI_F * (float)k / (float)t->ramp));
    }
    float x = w * sinf(TWO_PI * cycle_fraction(t->carrier_uhz, i, t->fs_hz));
    if (t->envelope_uhz > 0) {
        x *= 0.5f * (1.0f - cosf(TWO_PI * cycle_fraction(t->envelope_uhz, i, t->fs_hz)));
    }
    return x;
}

static uint32_t ramp_samples(uint32_t ramp_us, uint32_t fs_hz, uint32_t n)
{
    uint32_t r = us_to_samples(ramp_us, fs_hz);
    if (n) {
        uint32_t half = (n - 1) / 2;
        r = r < half ? r : half;
    }
    return r ? r : 1;
}

/* sup over [0, T] of the envelope (1 - cos(2 pi fe t))/2, T = last/fs (see synth.h) */
static float envelope_peak(int64_t envelope_uhz, uint32_t last, uint32_t fs_hz)
{
    if (envelope_uhz <= 0) {
        return 1.0f;
    }
    /* fe*T >= 1/2  <=>  2 * fe_uhz * last >= fs * 1e6 (fe_uhz < fs*1e6/2, last < 2^32) */
    int64_t half_period = (int64_t)fs_hz * 1000000;
    if ((int64_t)last >= (half_period + 2 * envelope_uhz - 1) / (2 * envelope_uhz)) {
        return 1.0f;
    }
    return 0.5f * (1.0f - cosf(TWO_PI * cycle_fraction(envelope_uhz, last, fs_hz)));
}

void tone_init(tone_t *t, int64_t carrier_uhz, int64_t envelope_uhz, uint32_t fs_hz,
               int64_t duration_us, uint32_t ramp_us)
{
    t->carrier_uhz = carrier_uhz;
    t->envelope_uhz = envelope_uhz;
    t->fs_hz = fs_hz;
    uint32_t s = us_to_samples(duration_us, fs_hz);
    t->n = s < UINT32_MAX ? s + 1 : s;
    t->ramp = ramp_samples(ramp_us, fs_hz, t->n);
    t->peak = t->n > 2 ? envelope_peak(envelope_uhz, t->n - 1, fs_hz) : 0.0f;
}

void tone_init_stream(tone_t *t, int64_t carrier_uhz, int64_t envelope_uhz, uint32_t fs_hz,
                      uint32_t ramp_us)
{
    t->carrier_uhz = carrier_uhz;
    t->envelope_uhz = envelope_uhz;
    t->fs_hz = fs_hz;
    t->n = 0;
    t->ramp = ramp_samples(ramp_us, fs_hz, 0);
    t->peak = 1.0f;
}

float tone_code(const tone_t *t, uint32_t i, int64_t code_amp)
{
    if (!(t->peak > 0.0f) || code_amp == 0 || (t->n && i >= t->n)) {
        return 0.0f;
    }
    return tone_unit(t, i) / t->peak * (float)code_amp;
}
