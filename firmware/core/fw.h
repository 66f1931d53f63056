/* The device: protocol v1 command handling, trial scheduling, safety rules.
 * See docs/device-protocol.md. One static instance per board; no heap. */
#ifndef ML_FW_H
#define ML_FW_H

#include <stdbool.h>
#include <stdint.h>

#include "frame.h"
#include "prng.h"
#include "synth.h"
#include "trial.h"

#define FW_PROTOCOL_VERSION 1
#define FW_VERSION "fw-1.0.0"

typedef struct {
    int64_t limit_uv[CH_COUNT]; /* the device's own per-channel limit, µV */
    uint32_t wd_ms;             /* host-quiet watchdog period, ms; 0 = none */
    uint32_t fs_hz;             /* sample rate */
    uint32_t ramp_us;           /* raised-cosine ramp of every tone */
    uint32_t jitter_us;         /* virtual time: largest simulated onset lateness */
    uint32_t seed;              /* virtual time: lateness generator seed */
    bool virtual_time;          /* PLAY completes at once; device clock = sum of trials */
    const char *fw_version;     /* reported in HELLO and BOOT */
    const char *model;
    const char *serial_number;
} fw_config_t;

typedef struct {
    bool active;
    tone_t tone;
    int64_t t0_us; /* device time of SETUP: the stream's phase origin */
} stream_t;

typedef struct {
    fw_config_t cfg;
    line_rx_t rx;
    command_t cmd;
    frame_tx_t tx;
    int64_t amp_uv[CH_COUNT]; /* present peak drive per channel (DIAG, watchdog arming) */
    stream_t stream[CH_COUNT];
    trial_t trial;
    bool playing;
    uint16_t event_no;
    uint64_t last_rx_mono_us;
    int64_t vt_us;
    bool interlock_open;
    uint32_t wd_trips;
    uint32_t faults;
    prng_t prng;
} fw_t;

void fw_init(fw_t *fw, const fw_config_t *cfg, bool interlock_open);
/* Announce a (re)start: "!n BOOT fw=...". */
void fw_boot(fw_t *fw);
/* Bytes from the host link. */
void fw_rx(fw_t *fw, const uint8_t *data, size_t len);
/* Timed work: trial steps, watchdog. Call at least every millisecond or at fw_next_due(). */
void fw_poll(fw_t *fw);
/* Monotonic µs when fw_poll() has work next (UINT64_MAX: nothing scheduled). */
uint64_t fw_next_due(const fw_t *fw);
/* The interlock input changed (or was sampled): open zeroes and refuses output. */
void fw_set_interlock(fw_t *fw, bool open);
/* The host link dropped (board-detected): zero like HELLO does. */
void fw_link_lost(fw_t *fw);
/* Device time now, µs (virtual or real). */
int64_t fw_now_us(const fw_t *fw);
/* Drive of both channels (V) at device time t_us: what the DAC must output then. */
void fw_render(const fw_t *fw, int64_t t_us, float out[CH_COUNT]);

#endif
