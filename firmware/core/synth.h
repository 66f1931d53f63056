/* Waveform synthesis matching masking_lab.waveforms (tone, ramp_window, trial_buffers).
 *
 * A tone of duration D at sample rate fs has N = round(D*fs) + 1 samples; sample i is
 *   unit(i) = w(i) * sin(2*pi*fc*i/fs) * [ (1 - cos(2*pi*fe*i/fs)) / 2 ]
 * with w the raised-cosine ramp (r = max(1, min(round(ramp*fs), (N-1)/2)) samples, w(N-1)=0).
 *
 * The tone is scaled by code_amp / peak, where `peak` bounds |unit| over the WHOLE tone in
 * closed form (tone_init, O(1)): 0 <= w <= 1 and |sin| <= 1, and the envelope
 * (1 - cos)/2 rises monotonically to 1 at t = 1/(2 fe), so its supremum over [0, T],
 * T = (N-1)/fs, is 1 if fe*T >= 1/2 and (1 - cos(2 pi fe T))/2 otherwise (1 without an
 * envelope). So no sample exceeds code_amp, whatever the length; no scan over the samples is
 * needed (the PLAY handler does constant work) and synthesis happens sample by sample in the
 * output stage's refill. The carrier phase is computed from integers (µHz * i mod fs*1e6) so
 * it never drifts, even in single-precision float on a Cortex-M4. */
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
    float peak;           /* closed-form bound of |unit| over the tone (0: silent) */
} tone_t;

/* Prepare a finite tone: sample count, ramp and the closed-form peak bound (O(1)). */
void tone_init(tone_t *t, int64_t carrier_uhz, int64_t envelope_uhz, uint32_t fs_hz,
               int64_t duration_us, uint32_t ramp_us);

/* Prepare an endless stream tone: ramp-in only, peak bound 1. */
void tone_init_stream(tone_t *t, int64_t carrier_uhz, int64_t envelope_uhz, uint32_t fs_hz,
                      uint32_t ramp_us);

/* The unit waveform (before scaling) at sample i (0 outside the tone). */
float tone_unit(const tone_t *t, uint32_t i);

/* Sample i in converter codes for a code amplitude (unit/peak * code_amp; 0 outside). */
float tone_code(const tone_t *t, uint32_t i, int64_t code_amp);

/* round(us * fs / 1e6): the sample index of a time offset (saturating). */
uint32_t us_to_samples(int64_t us, uint32_t fs_hz);

#endif
