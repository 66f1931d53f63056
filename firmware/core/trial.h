/* One three-interval (n-interval) trial: its plan, schedule and samples. */
#ifndef ML_TRIAL_H
#define ML_TRIAL_H

#include <stdbool.h>
#include <stdint.h>

#include "synth.h"

#define TRIAL_MAX_INTERVALS 9
#define TRIAL_MAX_DURATION_US (60LL * 1000000LL)
/* How far ahead of the device clock a PLAY may be scheduled. In real time a trial armed more
 * than 60 s ahead is a host error; in virtual time the clock moves only at PLAY, so the gap
 * covers the participant's responses and breaks since the last trial (bounded at one day). */
#define TRIAL_MAX_AHEAD_RT_US TRIAL_MAX_DURATION_US
#define TRIAL_MAX_AHEAD_VT_US (86400LL * 1000000LL)

enum { CH_EV = 0, CH_MV = 1, CH_COUNT = 2 };

typedef struct {
    int ch;               /* CH_EV / CH_MV; -1 = no masker */
    int64_t carrier_uhz;
    int64_t envelope_uhz; /* 0 = none */
    int64_t amp_uv;       /* requested peak at the amplifier input */
    uint8_t att_idx;      /* attenuator step (index into the board's list) */
    int64_t code_amp;     /* peak in converter codes (level_code) */
    int64_t played_uv;    /* what code_amp plays at the amplifier input (DONE) */
} part_t;

typedef struct {
    uint16_t seq;                  /* of the PLAY */
    part_t target, masker;
    int ti, n;                     /* target interval 1..n, number of intervals */
    int64_t stim_us, gap_us, lead_us; /* each validated to 0..60 s before any sum */
    int64_t start_us;              /* device time of the trial start */
    int64_t planned_us[TRIAL_MAX_INTERVALS];
    int64_t actual_us[TRIAL_MAX_INTERVALS]; /* when the output stage played each onset */
    bool onset_seen[TRIAL_MAX_INTERVALS];
    int step;                      /* next step: 2k = onset of interval k, 2k+1 = its offset */
    tone_t target_tone, masker_tone;
} trial_t;

/* lead + n*stim + (n-1)*gap, saturating (never wraps whatever the fields). */
int64_t trial_duration_us(const trial_t *t);

/* Planned onsets from start_us: start + lead + k*(stim + gap). */
void trial_schedule(trial_t *t, int64_t start_us);

/* Device time of step `step` (onset or offset). */
int64_t trial_step_time(const trial_t *t, int step);

/* Prepare the tones for rendering: O(1), closed-form peak bounds (synth.h). */
void trial_prepare_tones(trial_t *t, uint32_t fs_hz, uint32_t ramp_us);

/* Both channels at device time t_us, in converter codes; tones add when they share a
 * channel. Records the device time at which each interval's first sample is rendered. */
void trial_render(trial_t *t, int64_t t_us, uint32_t fs_hz, float code[CH_COUNT]);

#endif
