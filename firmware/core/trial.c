#include "trial.h"

int64_t trial_duration_us(const trial_t *t)
{
    return t->lead_us + t->n * t->stim_us + (t->n - 1) * t->gap_us;
}

void trial_schedule(trial_t *t, int64_t start_us)
{
    t->start_us = start_us;
    for (int k = 0; k < t->n; k++) {
        t->planned_us[k] = start_us + t->lead_us + k * (t->stim_us + t->gap_us);
        t->actual_us[k] = 0;
    }
    t->step = 0;
}

int64_t trial_step_time(const trial_t *t, int step)
{
    int64_t onset = t->planned_us[step / 2];
    return (step % 2) ? onset + t->stim_us : onset;
}

void trial_prepare_tones(trial_t *t, uint32_t fs_hz, uint32_t ramp_us)
{
    tone_init(&t->target_tone, t->target.carrier_uhz, t->target.envelope_uhz, fs_hz, t->stim_us,
              ramp_us, t->target.amp_uv);
    if (t->masker.ch >= 0) {
        tone_init(&t->masker_tone, t->masker.carrier_uhz, t->masker.envelope_uhz, fs_hz,
                  t->stim_us, ramp_us, t->masker.amp_uv);
    }
}

void trial_render(const trial_t *t, int64_t t_us, uint32_t fs_hz, float out[CH_COUNT])
{
    out[CH_EV] = out[CH_MV] = 0.0f;
    /* intervals are placed on the sample grid of the trial start, like trial_buffers() */
    int64_t rel = t_us - t->start_us;
    if (rel < 0) {
        return;
    }
    uint32_t s = us_to_samples(rel, fs_hz);
    for (int k = 0; k < t->n; k++) {
        uint32_t on = us_to_samples(t->planned_us[k] - t->start_us, fs_hz);
        if (s < on) {
            break;
        }
        uint32_t i = s - on;
        if (k + 1 == t->ti) {
            out[t->target.ch] += tone_sample(&t->target_tone, i);
        }
        if (t->masker.ch >= 0) {
            out[t->masker.ch] += tone_sample(&t->masker_tone, i);
        }
    }
}
