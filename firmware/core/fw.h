/* The device: protocol v2 command handling, trial scheduling, safety rules.
 * See docs/device-protocol.md. One static instance per board; no heap. */
#ifndef ML_FW_H
#define ML_FW_H

#include <stdbool.h>
#include <stdint.h>

#include "frame.h"
#include "level.h"
#include "prng.h"
#include "synth.h"
#include "trial.h"

#define FW_PROTOCOL_VERSION 2
#define FW_VERSION "fw-2.0.0"
#ifndef FW_BUILD
#define FW_BUILD "000000000000" /* the Makefile passes a hash of the firmware sources */
#endif

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
    /* v2: converter and attenuators per channel (0 / empty = defaults: 12 bits, 10 V, {0}) */
    uint8_t bits[CH_COUNT];
    int64_t fsv_uv[CH_COUNT];         /* full scale at the amplifier input, µV peak */
    uint8_t att_db[LEVEL_MAX_STEPS];  /* attenuator steps, dB ascending, first 0 */
    uint8_t n_att;
    /* largest |code| around mid-scale the output stage plays linearly, per channel (HELLO
     * lin=EV,MV); 0 = level_default_linear(bits). Every code limit (command checks and
     * the per-sample check in fw_render) is capped by it, at every attenuator step. */
    int64_t lin_code[CH_COUNT];
    const char *build;                /* 12 hex digits (FW_BUILD if NULL) */
    uint32_t test_overdrive_pct;      /* fault injection (host build tests only): 0 = off */
    bool vt_render;                   /* virtual time: still render every trial's samples
                                       * through fw_render (host build: corpus, tests) */
} fw_config_t;

typedef struct {
    bool active;
    tone_t tone;
    int64_t t0_us;    /* device time of SETUP: the stream's phase origin */
    int64_t code_amp; /* streamed amplitude in converter codes (att step 0) */
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
    converter_t conv[CH_COUNT];
    uint8_t att_idx[CH_COUNT];   /* attenuator step in force per channel */
    int64_t code_limit[CH_COUNT]; /* largest |code| within the channel limit at att_idx */
    float v_per_code[CH_COUNT];  /* V at the amplifier input per code at att_idx */
    int32_t out_code[CH_COUNT];  /* last rendered sample, signed codes around mid-scale */
    bool limit_tripped;          /* a rendered sample was over its limit: FAULT pending */
    /* work measured on the device clock since the last DIAG (under QEMU -icount shift=0 one
     * µs is 1000 instructions): longest command handler, longest fw_poll, longest refill of
     * the output stage (first fw_render after a poll to the next poll), samples rendered */
    uint64_t handler_max_us, poll_max_us, refill_max_us, render_samples, render_t0_us;
    bool render_open;
    int64_t peak_code[CH_COUNT]; /* largest |code| since the attenuators last changed */
    int64_t peak_uv[CH_COUNT];   /* largest |sample| output since boot, µV (DIAG pk_ev/pk_mv) */
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
/* Text of `ERR SIZE`, sent in place of a reply that would not fit in FRAME_MAX_BYTES
 * (an event that would not fit becomes `FAULT code=SIZE`). */
#define FW_SIZE_TEXT "reply longer than 256 bytes not sent"
/* Whether this configuration's HELLO fits in one frame at the longest seq (65535). A build
 * whose HELLO does not fit must refuse to start: shorten the serial number (or model). */
bool fw_hello_fits(fw_t *fw);
/* Device time now, µs (virtual or real). */
int64_t fw_now_us(const fw_t *fw);
/* The board's output-stage refill (its run of fw_render() calls) has ended: record how long
 * it took (DIAG omax_us). Call it right after the refill, before the board sleeps. */
void fw_refill_end(fw_t *fw);
/* Drive of both channels (V at the amplifier input) at device time t_us: what the output
 * stage must play then; fw->out_code[] holds the same samples as signed converter codes.
 * Every sample is checked against the channel's limit first: one over it is never output
 * (both 0, FAULT code=LIMIT sent by the next fw_poll()). Call from the DMA refill / output
 * stage, one block at a time: this is where all synthesis happens. */
void fw_render(fw_t *fw, int64_t t_us, float out[CH_COUNT]);

#endif
