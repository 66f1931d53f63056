#include "synth.h"

#include <math.h>

#define TWO_PI 6.28318530717958647692f
#define PI_F 3.14159265358979323846f
#define PEAK_SCAN_S 2u

uint32_t us_to_samples(int64_t us, uint32_t fs_hz)
{
    if (us <= 0) {
        return 0;
    }
    return (uint32_t)(((uint64_t)us * fs_hz + 500000u) / 1000000u);
}

/* fraction of a cycle of frequency f_uhz after i samples, in [0, 1) */
static float cycle_fraction(int64_t f_uhz, uint32_t i, uint32_t fs_hz)
{
    int64_t period = (int64_t)fs_hz * 1000000;
    int64_t ph = (f_uhz % period) * (int64_t)i % period;
    return (float)ph / (float)period;
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

void tone_init(tone_t *t, int64_t carrier_uhz, int64_t envelope_uhz, uint32_t fs_hz,
               int64_t duration_us, uint32_t ramp_us, int64_t amp_uv)
{
    t->carrier_uhz = carrier_uhz;
    t->envelope_uhz = envelope_uhz;
    t->fs_hz = fs_hz;
    t->n = us_to_samples(duration_us, fs_hz) + 1;
    t->ramp = ramp_samples(ramp_us, fs_hz, t->n);
    t->scale = 0.0f;
    if (amp_uv <= 0) {
        return;
    }
    /* The peak is searched over the first PEAK_SCAN_S of the tone: the whole tone for every
     * stimulus of the paper (1.8 s), and for a longer one the remaining samples could only
     * raise the sampled peak by < 1e-6 relative; scanning 20 s would stall the PLAY handler
     * for a second on a Cortex-M4. */
    uint32_t scan = t->n < fs_hz * PEAK_SCAN_S ? t->n : fs_hz * PEAK_SCAN_S;
    float peak = 0.0f;
    for (uint32_t i = 0; i < scan; i++) {
        float a = fabsf(tone_unit(t, i));
        peak = a > peak ? a : peak;
    }
    if (peak > 0.0f) {
        t->scale = (float)amp_uv / 1e6f / peak;
    }
}

void tone_init_stream(tone_t *t, int64_t carrier_uhz, int64_t envelope_uhz, uint32_t fs_hz,
                      uint32_t ramp_us)
{
    t->carrier_uhz = carrier_uhz;
    t->envelope_uhz = envelope_uhz;
    t->fs_hz = fs_hz;
    t->n = 0;
    t->ramp = ramp_samples(ramp_us, fs_hz, 0);
    t->scale = 1.0f;
}

float tone_sample(const tone_t *t, uint32_t i)
{
    if (t->scale == 0.0f || (t->n && i >= t->n)) {
        return 0.0f;
    }
    return tone_unit(t, i) * t->scale;
}
