/* Command handlers of protocol v2. Validation order follows the Python emulator so
 * both give the same ERR code for the same bad command: INTERLOCK, then fields (ARGS), then
 * BUSY/STATE, then limits (LIMIT). Every ERR zeroes both outputs (fw_err). */
#include <stdarg.h>
#include <string.h>

#include "board.h"
#include "clock.h"
#include "fixed.h"
#include "fw_internal.h"
#include "level.h"

typedef struct {
    fw_t *fw;
    const command_t *cmd;
    bool failed; /* an ERR was already sent */
} ctx_t;

static const char *const CH_NAME[CH_COUNT] = {"EV", "MV"};

/* Join NULL-terminated pieces into buf (truncating): snprintf would pull malloc into newlib. */
static const char *join(char *buf, size_t cap, const char *first, ...)
{
    va_list ap;
    size_t n = 0;
    va_start(ap, first);
    for (const char *s = first; s; s = va_arg(ap, const char *)) {
        while (*s && n + 1 < cap) {
            buf[n++] = *s++;
        }
    }
    va_end(ap);
    buf[n] = '\0';
    return buf;
}

static void args_err(ctx_t *c, const char *what, const char *key)
{
    if (c->failed) {
        return;
    }
    char text[96];
    fw_err(c->fw, c->cmd->seq, "ARGS",
           join(text, sizeof text, c->cmd->name, ": ", key, " ", what, (const char *)NULL));
    c->failed = true;
}

static int64_t number(ctx_t *c, const char *key)
{
    const char *v = command_field(c->cmd, key);
    int64_t out = 0;
    if (!v) {
        args_err(c, "is missing", key);
    } else if (!fx_parse(v, &out)) {
        args_err(c, "is not a plain decimal number", key);
    }
    return out;
}

static int channel(ctx_t *c, const char *key)
{
    const char *v = command_field(c->cmd, key);
    for (int ch = 0; v && ch < CH_COUNT; ch++) {
        if (strcmp(v, CH_NAME[ch]) == 0) {
            return ch;
        }
    }
    args_err(c, "is not EV or MV", key);
    return 0;
}

/* 0 < carrier < fs/2 and 0 <= envelope < fs/2 (µHz) */
static void check_frequency(ctx_t *c, int64_t car, int64_t env)
{
    int64_t nyquist = (int64_t)c->fw->cfg.fs_hz * FX_ONE / 2;
    if (!(car > 0 && car < nyquist) || !(env >= 0 && env < nyquist)) {
        args_err(c, "out of range: frequencies must be in (0, fs/2) Hz", "car/env");
    }
}

static bool interlock_ok(fw_t *fw, const command_t *cmd)
{
    if (!fw->interlock_open) {
        return true;
    }
    fw_err(fw, cmd->seq, "INTERLOCK",
           "interlock open: check HV enable, E-stop and the grounding wristband");
    return false;
}

static void limit_err(fw_t *fw, uint16_t seq, int ch, int64_t amp_uv, const char *what)
{
    char a[24], l[24], text[112];
    fx_format(a, sizeof a, amp_uv);
    fx_format(l, sizeof l, fw->cfg.limit_uv[ch]);
    fw_err(fw, seq, "LIMIT",
           join(text, sizeof text, CH_NAME[ch], " amplitude ", a, " V ", what, " the ", l,
                " V limit", (const char *)NULL));
}

/* A level whose code lies beyond the output stage's linear range (HELLO lin): it
 * could only be played clipped. Names the level, the step and the range in codes and volts. */
static void linear_err(fw_t *fw, uint16_t seq, int ch, int64_t amp_uv, uint8_t att_db)
{
    char a[24], d[24], n[24], v[24], text[160];
    int64_t lin = fw->cfg.lin_code[ch];
    fx_format(a, sizeof a, amp_uv);
    fx_format(d, sizeof d, (int64_t)att_db * FX_ONE);
    fx_format(n, sizeof n, lin * FX_ONE);
    fx_format(v, sizeof v, level_played_uv(&fw->conv[ch], lin, att_db));
    fw_err(fw, seq, "LIMIT",
           join(text, sizeof text, CH_NAME[ch], " amplitude ", a, " V at ", d,
                " dB exceeds the output's linear range of ", n, " codes (", v, " V)",
                (const char *)NULL));
}

/* Requested amp_uv (>= 0) on channel ch behind step att_idx: within the limit both as asked
 * and as quantised, and within the converter's range? Sets *code and *played. */
static bool level_ok(fw_t *fw, uint16_t seq, int ch, int64_t amp_uv, uint8_t att_idx,
                     int64_t *code, int64_t *played)
{
    if (amp_uv > fw->cfg.limit_uv[ch]) {
        limit_err(fw, seq, ch, amp_uv, "exceeds");
        return false;
    }
    uint8_t att = fw->cfg.att_db[att_idx];
    *code = level_code(&fw->conv[ch], amp_uv, att);
    *played = level_played_uv(&fw->conv[ch], *code, att);
    if (*played > fw->cfg.limit_uv[ch]) {
        limit_err(fw, seq, ch, amp_uv, "quantised at this attenuation exceeds");
        return false;
    }
    if (*code > fw->cfg.lin_code[ch]) {
        linear_err(fw, seq, ch, amp_uv, att);
        return false;
    }
    return true;
}

/* amplitude field: a peak >= 0 V (ARGS otherwise; its limit is checked later) */
static int64_t amplitude(ctx_t *c, const char *key)
{
    int64_t v = number(c, key);
    if (!c->failed && v < 0) {
        args_err(c, "must be >= 0 V", key);
    }
    return v;
}

/* duration field: 0 <= value <= 60 s (> 0 with `positive`), checked before any arithmetic */
static int64_t duration(ctx_t *c, const char *key, bool positive)
{
    int64_t v = number(c, key);
    if (!c->failed && (v < 0 || (positive && v == 0) || v > TRIAL_MAX_DURATION_US)) {
        args_err(c, positive ? "out of range: need 0 < value <= 60 s"
                             : "out of range: need 0 <= value <= 60 s",
                 key);
    }
    return v;
}

/* optional attenuation field: one of the board's steps (index returned), default 0 dB */
static uint8_t attenuation(ctx_t *c, const char *key)
{
    const char *v = command_field(c->cmd, key);
    if (!v) {
        return 0;
    }
    int64_t db = 0;
    if (!fx_parse(v, &db)) {
        args_err(c, "is not a plain decimal number", key);
        return 0;
    }
    for (uint8_t k = 0; k < c->fw->cfg.n_att; k++) {
        if (db == (int64_t)c->fw->cfg.att_db[k] * FX_ONE) {
            return k;
        }
    }
    args_err(c, "is not one of the board's attenuation steps (HELLO att)", key);
    return 0;
}

static void ok_begin(fw_t *fw, uint16_t seq)
{
    frame_begin_reply(&fw->tx, seq, true);
}

/* HELLO's fields into fw->tx (not sent). */
static void hello_build(fw_t *fw, uint16_t seq)
{
    ok_begin(fw, seq);
    frame_add_int(&fw->tx, "proto", FW_PROTOCOL_VERSION);
    frame_add_str(&fw->tx, "fw", fw->cfg.fw_version);
    frame_add_str(&fw->tx, "model", fw->cfg.model);
    frame_add_str(&fw->tx, "sn", fw->cfg.serial_number);
    frame_add_micro(&fw->tx, "max_ev", fw->cfg.limit_uv[CH_EV]);
    frame_add_micro(&fw->tx, "max_mv", fw->cfg.limit_uv[CH_MV]);
    frame_add_int(&fw->tx, "wd_ms", fw->cfg.wd_ms);
    frame_add_int(&fw->tx, "fs", fw->cfg.fs_hz);
    frame_add_int(&fw->tx, "vt", fw->cfg.virtual_time ? 1 : 0);
    frame_add_str(&fw->tx, "il", fw->interlock_open ? "open" : "closed");
    frame_add_str(&fw->tx, "build", fw->cfg.build);
    frame_add_str(&fw->tx, "clk", board_clock_source());
    frame_add_str(&fw->tx, "rst", board_reset_cause());
    frame_add_int(&fw->tx, "bits_ev", fw->conv[CH_EV].bits);
    frame_add_int(&fw->tx, "bits_mv", fw->conv[CH_MV].bits);
    frame_add_micro(&fw->tx, "fsv_ev", fw->conv[CH_EV].fsv_uv);
    frame_add_micro(&fw->tx, "fsv_mv", fw->conv[CH_MV].fsv_uv);
    int64_t att[LEVEL_MAX_STEPS];
    for (int k = 0; k < fw->cfg.n_att; k++) {
        att[k] = (int64_t)fw->cfg.att_db[k] * FX_ONE;
    }
    frame_add_micro_list(&fw->tx, "att", att, fw->cfg.n_att);
    /* linear range per channel, codes around mid-scale (EV,MV): one field keeps HELLO short */
    int64_t lin[CH_COUNT] = {fw->cfg.lin_code[CH_EV] * FX_ONE, fw->cfg.lin_code[CH_MV] * FX_ONE};
    frame_add_micro_list(&fw->tx, "lin", lin, CH_COUNT);
}

bool fw_hello_fits(fw_t *fw)
{
    hello_build(fw, 65535); /* the longest sequence number */
    bool fits = !fw->tx.overflow;
    frame_begin_reply(&fw->tx, 0, true); /* leave no half-built frame behind */
    return fits;
}

static void cmd_hello(fw_t *fw, const command_t *cmd)
{
    fw_zero(fw, NULL); /* a new host session starts from silence */
    hello_build(fw, cmd->seq);
    fw_send_frame(fw);
}

static void cmd_time(fw_t *fw, const command_t *cmd)
{
    ok_begin(fw, cmd->seq);
    frame_add_micro(&fw->tx, "t", fw_now_us(fw));
    fw_send_frame(fw);
}

static void cmd_stop(fw_t *fw, const command_t *cmd)
{
    fw_zero(fw, "STOP");
    ok_begin(fw, cmd->seq);
    fw_send_frame(fw);
}

static void cmd_diag(fw_t *fw, const command_t *cmd)
{
    float dac[CH_COUNT];
    board_dac_last(dac);
    ok_begin(fw, cmd->seq);
    frame_add_micro(&fw->tx, "ev", fw->amp_uv[CH_EV]);
    frame_add_micro(&fw->tx, "mv", fw->amp_uv[CH_MV]);
    frame_add_int(&fw->tx, "playing", fw->playing ? 1 : 0);
    frame_add_str(&fw->tx, "il", fw->interlock_open ? "open" : "closed");
    frame_add_micro(&fw->tx, "dac_ev", (int64_t)(dac[CH_EV] * 1e6f));
    frame_add_micro(&fw->tx, "dac_mv", (int64_t)(dac[CH_MV] * 1e6f));
    frame_add_int(&fw->tx, "wd", fw->wd_trips);
    frame_add_micro(&fw->tx, "t", fw_now_us(fw));
    frame_add_micro(&fw->tx, "pk_ev", fw->peak_uv[CH_EV]);
    frame_add_micro(&fw->tx, "pk_mv", fw->peak_uv[CH_MV]);
    /* work since the last DIAG (µs of device clock): see fw.h */
    frame_add_int(&fw->tx, "hmax_us", (int64_t)fw->handler_max_us);
    frame_add_int(&fw->tx, "pmax_us", (int64_t)fw->poll_max_us);
    frame_add_int(&fw->tx, "omax_us", (int64_t)fw->refill_max_us);
    frame_add_int(&fw->tx, "rnd_n", (int64_t)fw->render_samples);
    fw_send_frame(fw);
    fw->handler_max_us = fw->poll_max_us = fw->refill_max_us = fw->render_samples = 0;
}

static void cmd_setup(fw_t *fw, const command_t *cmd)
{
    ctx_t c = {fw, cmd, false};
    if (!interlock_ok(fw, cmd)) {
        return;
    }
    int ch = channel(&c, "ch");
    int64_t car = number(&c, "car"), env = number(&c, "env"), amp = amplitude(&c, "amp");
    if (!c.failed) {
        check_frequency(&c, car, env);
    }
    if (c.failed) {
        return;
    }
    if (fw->playing) {
        fw_err(fw, cmd->seq, "BUSY", "SETUP while a trial is playing");
        return;
    }
    int64_t code, played;
    if (!level_ok(fw, cmd->seq, ch, amp, 0, &code, &played)) {
        return;
    }
    if (fw->att_idx[ch] != 0) { /* streams play at the 0 dB step */
        fw->att_idx[ch] = 0;
        fw_apply_attenuators(fw);
    }
    stream_t *s = &fw->stream[ch];
    s->code_amp = code;
    tone_init_stream(&s->tone, car, env, fw->cfg.fs_hz, fw->cfg.ramp_us);
    s->t0_us = fw_now_us(fw);
    s->active = true;
    fw->amp_uv[ch] = played;
    ok_begin(fw, cmd->seq);
    fw_send_frame(fw);
}

static void cmd_amp(fw_t *fw, const command_t *cmd)
{
    ctx_t c = {fw, cmd, false};
    if (!interlock_ok(fw, cmd)) {
        return;
    }
    int ch = channel(&c, "ch");
    int64_t amp = amplitude(&c, "amp");
    if (c.failed) {
        return;
    }
    if (fw->playing) {
        fw_err(fw, cmd->seq, "BUSY", "AMP while a trial is playing");
        return;
    }
    if (!fw->stream[ch].active) {
        char text[48];
        fw_err(fw, cmd->seq, "STATE",
               join(text, sizeof text, "AMP on ", CH_NAME[ch], " before SETUP of ", CH_NAME[ch],
                    (const char *)NULL));
        return;
    }
    int64_t code, played;
    if (!level_ok(fw, cmd->seq, ch, amp, 0, &code, &played)) {
        return;
    }
    fw->stream[ch].code_amp = code;
    fw->amp_uv[ch] = played;
    ok_begin(fw, cmd->seq);
    fw_send_frame(fw);
}

/* Fill a plan from a PLAY's fields; false (ERR ARGS sent) if one is bad. Every duration is
 * bounded (0..60 s) before it enters a sum, so no arithmetic here can overflow. */
static bool parse_plan(ctx_t *c, trial_t *t, int64_t *at)
{
    t->target.ch = channel(c, "tch");
    t->target.carrier_uhz = number(c, "tcar");
    t->target.envelope_uhz = number(c, "tenv");
    t->target.amp_uv = amplitude(c, "tamp");
    if (!c->failed) {
        check_frequency(c, t->target.carrier_uhz, t->target.envelope_uhz);
    }
    const char *mch = command_field(c->cmd, "mch");
    t->masker.ch = -1;
    t->masker.amp_uv = 0;
    if (mch && strcmp(mch, "-") != 0) {
        t->masker.ch = channel(c, "mch");
        t->masker.carrier_uhz = number(c, "mcar");
        t->masker.envelope_uhz = number(c, "menv");
        if (!c->failed) {
            check_frequency(c, t->masker.carrier_uhz, t->masker.envelope_uhz);
        }
        t->masker.amp_uv = amplitude(c, "mamp");
    }
    int64_t n = number(c, "n") / FX_ONE, ti = number(c, "ti") / FX_ONE; /* int() truncates */
    if (!c->failed && !(ti >= 1 && ti <= n && n <= TRIAL_MAX_INTERVALS)) {
        args_err(c, "out of range: need 1 <= ti <= n <= 9", "ti/n");
    }
    t->n = c->failed ? 0 : (int)n;
    t->ti = c->failed ? 0 : (int)ti;
    t->stim_us = duration(c, "stim", true);
    t->gap_us = duration(c, "gap", false);
    t->lead_us = duration(c, "lead", false);
    if (!c->failed && trial_duration_us(t) > TRIAL_MAX_DURATION_US) {
        args_err(c, "bad: need lead + n*stim + (n-1)*gap <= 60 s", "durations");
    }
    *at = number(c, "at");
    int64_t ahead = c->fw->cfg.virtual_time ? TRIAL_MAX_AHEAD_VT_US : TRIAL_MAX_AHEAD_RT_US;
    if (!c->failed && (*at < 0 || *at > clock_add_sat(fw_now_us(c->fw), ahead))) {
        args_err(c, c->fw->cfg.virtual_time ? "out of range: need 0 <= at <= device time + 1 day"
                                            : "out of range: need 0 <= at <= device time + 60 s",
                 "at");
    }
    t->target.att_idx = attenuation(c, "tatt");
    t->masker.att_idx = t->masker.ch >= 0 ? attenuation(c, "matt") : 0;
    if (!c->failed && t->masker.ch == t->target.ch && t->masker.att_idx != t->target.att_idx) {
        args_err(c, "must equal tatt when target and masker share a channel", "matt");
    }
    return !c->failed;
}

/* Quantise both parts and check each channel's sum, asked and as played, against its limit
 * (ERR LIMIT sent if not). */
static bool plan_levels(fw_t *fw, uint16_t seq, trial_t *t)
{
    part_t *parts[2] = {&t->target, t->masker.ch >= 0 ? &t->masker : NULL};
    int64_t asked[CH_COUNT] = {0, 0}, code[CH_COUNT] = {0, 0}, played[CH_COUNT] = {0, 0};
    uint8_t ch_att[CH_COUNT] = {0, 0};
    for (int k = 0; k < 2; k++) {
        part_t *p = parts[k];
        if (!p) {
            continue;
        }
        asked[p->ch] += p->amp_uv; /* each <= 1e18 after fx_parse: the sum fits */
        ch_att[p->ch] = p->att_idx;
        if (p->amp_uv > fw->cfg.limit_uv[p->ch]) {
            continue; /* refused below, before any quantisation */
        }
        uint8_t att = fw->cfg.att_db[p->att_idx];
        p->code_amp = level_code(&fw->conv[p->ch], p->amp_uv, att);
        p->played_uv = level_played_uv(&fw->conv[p->ch], p->code_amp, att);
        code[p->ch] += p->code_amp;
        played[p->ch] += p->played_uv;
    }
    for (int ch = 0; ch < CH_COUNT; ch++) {
        if (asked[ch] > fw->cfg.limit_uv[ch]) {
            limit_err(fw, seq, ch, asked[ch], "exceeds");
            return false;
        }
        if (played[ch] > fw->cfg.limit_uv[ch]) {
            limit_err(fw, seq, ch, asked[ch], "quantised at this attenuation exceeds");
            return false;
        }
        if (code[ch] > fw->cfg.lin_code[ch]) { /* both parts share the channel's step */
            linear_err(fw, seq, ch, asked[ch], fw->cfg.att_db[ch_att[ch]]);
            return false;
        }
    }
    return true;
}

/* Virtual time with vt_render: push every sample of the trial through the output stage's
 * checks (host build only: this is the long work a real board does in its DMA refill). */
static bool vt_render(fw_t *fw, int64_t end)
{
    trial_t *t = &fw->trial;
    float out[CH_COUNT];
    trial_prepare_tones(t, fw->cfg.fs_hz, fw->cfg.ramp_us);
    fw->playing = true;
    uint32_t n = us_to_samples(end - t->start_us, fw->cfg.fs_hz);
    for (uint32_t i = 0; i <= n && !fw->limit_tripped; i++) {
        int64_t t_us = t->start_us + (int64_t)((uint64_t)i * 1000000u / fw->cfg.fs_hz);
        fw_render(fw, t_us, out);
        if ((i & 0x3FFu) == 0) {
            board_iwdg_feed(); /* a board spreads this work over the trial's refills */
        }
    }
    if (fw->limit_tripped) {
        fw_limit_fault(fw);
        return false;
    }
    fw->playing = false;
    board_outputs_zero();
    return true;
}

static void cmd_play(fw_t *fw, const command_t *cmd)
{
    ctx_t c = {fw, cmd, false};
    if (!interlock_ok(fw, cmd)) {
        return;
    }
    if (fw->playing) {
        fw_err(fw, cmd->seq, "BUSY", "PLAY while a trial is playing");
        return;
    }
    trial_t plan;
    memset(&plan, 0, sizeof plan);
    int64_t at = 0;
    if (!parse_plan(&c, &plan, &at) || !plan_levels(fw, cmd->seq, &plan)) {
        return;
    }
    /* PLAY owns the outputs: any stream stops first. */
    fw_zero(fw, NULL);
    plan.seq = cmd->seq;
    int64_t now = fw_now_us(fw);
    trial_schedule(&plan, at > now ? at : now);
    fw->trial = plan;
    trial_t *t = &fw->trial;
    fw->att_idx[t->target.ch] = t->target.att_idx;
    if (t->masker.ch >= 0) {
        fw->att_idx[t->masker.ch] = t->masker.att_idx;
    }
    fw_apply_attenuators(fw);
    ok_begin(fw, cmd->seq);
    frame_add_micro(&fw->tx, "start", t->start_us);
    fw_send_frame(fw);
    int64_t end = clock_add_sat(t->start_us, trial_duration_us(t));
    if (fw->cfg.virtual_time) {
        if (fw->cfg.vt_render && !vt_render(fw, end)) {
            return; /* FAULT code=LIMIT sent instead of DONE */
        }
        /* Nothing plays: report the planned onsets plus the documented lateness. */
        for (int k = 0; k < t->n; k++) {
            t->actual_us[k] = t->planned_us[k] + prng_lateness_us(&fw->prng, fw->cfg.jitter_us);
        }
        fw->vt_us = end > fw->vt_us ? end : fw->vt_us;
        fw_send_done(fw, end);
        return;
    }
    trial_prepare_tones(t, fw->cfg.fs_hz, fw->cfg.ramp_us);
    fw->playing = true;
}

void fw_dispatch(fw_t *fw, const command_t *cmd)
{
    static const struct {
        const char *name;
        void (*handler)(fw_t *, const command_t *);
    } table[] = {
        {"HELLO", cmd_hello}, {"TIME", cmd_time},   {"PING", cmd_time}, {"STOP", cmd_stop},
        {"SETUP", cmd_setup}, {"AMP", cmd_amp},     {"PLAY", cmd_play}, {"DIAG", cmd_diag},
    };
    for (size_t i = 0; i < sizeof table / sizeof table[0]; i++) {
        if (strcmp(cmd->name, table[i].name) == 0) {
            table[i].handler(fw, cmd);
            return;
        }
    }
    char text[64];
    fw_err(fw, cmd->seq, "UNKNOWN",
           join(text, sizeof text, "unknown command ", cmd->name, (const char *)NULL));
}
