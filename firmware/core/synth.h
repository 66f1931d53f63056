/* Waveform synthesis matching masking_lab.waveforms (tone, ramp_window, trial_buffers).
 *
 * A tone of duration D at sample rate fs has N = round(D*fs) + 1 samples; sample i is
 *   unit(i) = w(i) * sin(2*pi*fc*i/fs) * [ (1 - cos(2*pi*fe*i/fs)) / 2 ]
 * with w the raised-cosine ramp (r = max(1, min(round(ramp*fs), (N-1)/2)) samples, w(N-1)=0),
 * scaled by amplitude/peak where peak = max|unit| over the tone, so the largest sample is the
 * requested peak exactly, as in the Python code. The carrier phase is computed from integers
 * (µHz * i mod fs*1e6) so it never drifts, even in single-precision float on a Cortex-M4. */
#ifndef ML_SYNTH_H
#define ML_SYNTH_H

#include <stdbool.h>
#include <stdint.h>

typedef struct {
    int64_t carrier_uhz;  /* carrier, µHz */
    int64_t envelope_uhz; /* AM envelope, µHz; 0 = none */
    uint32_t fs_hz;
    uint32_t n;           /* samples in the tone; 0 = endless (a stream) */
    uint32_t ramp;        /* ramp length, samples */
    float scale;          /* amplitude (V) / peak of the unit waveform */
} tone_t;

/* Prepare a finite tone (computes the peak: one pass over the tone). */
void tone_init(tone_t *t, int64_t carrier_uhz, int64_t envelope_uhz, uint32_t fs_hz,
               int64_t duration_us, uint32_t ramp_us, int64_t amp_uv);

/* Prepare an endless stream tone: ramp-in only, amplitude scaled separately (peak 1). */
void tone_init_stream(tone_t *t, int64_t carrier_uhz, int64_t envelope_uhz, uint32_t fs_hz,
                      uint32_t ramp_us);

/* The unit waveform (before scaling) at sample i. */
float tone_unit(const tone_t *t, uint32_t i);

/* Sample i in V (0 outside the tone). */
float tone_sample(const tone_t *t, uint32_t i);

/* round(us * fs / 1e6): the sample index of a time offset. */
uint32_t us_to_samples(int64_t us, uint32_t fs_hz);

#endif
