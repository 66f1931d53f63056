#include "trial.h"

#include "clock.h"

static int64_t mul_sat(int64_t a, int64_t b)
{
    /* a, b >= 0 here */
    if (a != 0 && b > INT64_MAX / a) {
        return INT64_MAX;
    }
    return a * b;
}

int64_t trial_duration_us(const trial_t *t)
{
    if (t->n <= 0) {
        return t->lead_us;
    }
    int64_t d = clock_add_sat(t->lead_us, mul_sat(t->n, t->stim_us));
    return clock_add_sat(d, mul_sat(t->n - 1, t->gap_us));
}

void trial_schedule(trial_t *t, int64_t start_us)
{
    t->start_us = start_us;
    for (int k = 0; k < t->n; k++) {
        int64_t off = clock_add_sat(t->lead_us, mul_sat(k, clock_add_sat(t->stim_us, t->gap_us)));
        t->planned_us[k] = clock_add_sat(start_us, off);
        t->actual_us[k] = 0;
        t->onset_seen[k] = false;
    }
    t->step = 0;
}

int64_t trial_step_time(const trial_t *t, int step)
{
    int64_t onset = t->planned_us[step / 2];
    return (step % 2) ? clock_add_sat(onset, t->stim_us) : onset;
}

void trial_prepare_tones(trial_t *t, uint32_t fs_hz, uint32_t ramp_us)
{
    tone_init(&t->target_tone, t->target.carrier_uhz, t->target.envelope_uhz, fs_hz, t->stim_us,
              ramp_us);
    if (t->masker.ch >= 0) {
        tone_init(&t->masker_tone, t->masker.carrier_uhz, t->masker.envelope_uhz, fs_hz,
                  t->stim_us, ramp_us);
    }
}

void trial_render(trial_t *t, int64_t t_us, uint32_t fs_hz, float code[CH_COUNT])
{
    code[CH_EV] = code[CH_MV] = 0.0f;
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
        if (!t->onset_seen[k]) {
            t->onset_seen[k] = true; /* the output stage plays this interval from t_us */
            t->actual_us[k] = t_us;
        }
        if (k + 1 == t->ti) {
            code[t->target.ch] += tone_code(&t->target_tone, i, t->target.code_amp);
        }
        if (t->masker.ch >= 0) {
            code[t->masker.ch] += tone_code(&t->masker_tone, i, t->masker.code_amp);
        }
    }
}
