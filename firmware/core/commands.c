/* Command handlers of protocol v1 (+ DIAG). Validation order follows the Python emulator so
 * both give the same ERR code for the same bad command: INTERLOCK, then fields (ARGS), then
 * BUSY/STATE, then limits (LIMIT). Every ERR zeroes both outputs (fw_err). */
#include <stdarg.h>
#include <string.h>

#include "board.h"
#include "fixed.h"
#include "fw_internal.h"

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

static bool within_limit(fw_t *fw, uint16_t seq, int ch, int64_t amp_uv)
{
    if (amp_uv >= 0 && amp_uv <= fw->cfg.limit_uv[ch]) {
        return true;
    }
    char a[24], l[24], text[96];
    fx_format(a, sizeof a, amp_uv);
    fx_format(l, sizeof l, fw->cfg.limit_uv[ch]);
    fw_err(fw, seq, "LIMIT",
           join(text, sizeof text, CH_NAME[ch], " amplitude ", a, " V exceeds the ", l,
                " V limit", (const char *)NULL));
    return false;
}

static void ok_begin(fw_t *fw, uint16_t seq)
{
    frame_begin_reply(&fw->tx, seq, true);
}

static void cmd_hello(fw_t *fw, const command_t *cmd)
{
    fw_zero(fw, NULL); /* a new host session starts from silence */
    ok_begin(fw, cmd->seq);
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
    fw_send_frame(fw);
}

static void cmd_setup(fw_t *fw, const command_t *cmd)
{
    ctx_t c = {fw, cmd, false};
    if (!interlock_ok(fw, cmd)) {
        return;
    }
    int ch = channel(&c, "ch");
    int64_t car = number(&c, "car"), env = number(&c, "env"), amp = number(&c, "amp");
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
    if (!within_limit(fw, cmd->seq, ch, amp)) {
        return;
    }
    stream_t *s = &fw->stream[ch];
    tone_init_stream(&s->tone, car, env, fw->cfg.fs_hz, fw->cfg.ramp_us);
    s->t0_us = fw_now_us(fw);
    s->active = true;
    fw->amp_uv[ch] = amp;
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
    int64_t amp = number(&c, "amp");
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
    if (!within_limit(fw, cmd->seq, ch, amp)) {
        return;
    }
    fw->amp_uv[ch] = amp;
    ok_begin(fw, cmd->seq);
    fw_send_frame(fw);
}

/* Fill fw->trial from a PLAY; false (ERR sent) if a field is bad. */
static bool parse_plan(ctx_t *c, trial_t *t)
{
    t->target.ch = channel(c, "tch");
    t->target.carrier_uhz = number(c, "tcar");
    t->target.envelope_uhz = number(c, "tenv");
    t->target.amp_uv = number(c, "tamp");
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
        t->masker.amp_uv = number(c, "mamp");
    }
    int64_t n = number(c, "n") / FX_ONE, ti = number(c, "ti") / FX_ONE; /* int() truncates */
    if (!c->failed && !(ti >= 1 && ti <= n && n <= TRIAL_MAX_INTERVALS)) {
        args_err(c, "out of range: need 1 <= ti <= n <= 9", "ti/n");
    }
    t->n = (int)n;
    t->ti = (int)ti;
    t->stim_us = number(c, "stim");
    t->gap_us = number(c, "gap");
    t->lead_us = number(c, "lead");
    if (!c->failed && (t->stim_us <= 0 || t->gap_us < 0 || t->lead_us < 0 ||
                       trial_duration_us(t) > TRIAL_MAX_DURATION_US)) {
        args_err(c, "bad: need stim > 0, gap >= 0, lead >= 0, trial <= 60 s", "durations");
    }
    return !c->failed;
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
    if (!parse_plan(&c, &plan)) {
        return;
    }
    int64_t sum[CH_COUNT] = {0, 0};
    sum[plan.target.ch] += plan.target.amp_uv;
    if (plan.masker.ch >= 0) {
        sum[plan.masker.ch] += plan.masker.amp_uv;
    }
    for (int ch = 0; ch < CH_COUNT; ch++) {
        if (!within_limit(fw, cmd->seq, ch, sum[ch])) {
            return;
        }
    }
    int64_t at = number(&c, "at");
    if (c.failed) {
        return;
    }
    /* PLAY owns the outputs: any stream stops first. */
    fw_zero(fw, NULL);
    plan.seq = cmd->seq;
    int64_t now = fw_now_us(fw);
    trial_schedule(&plan, at > now ? at : now);
    fw->trial = plan;
    trial_t *t = &fw->trial;
    ok_begin(fw, cmd->seq);
    frame_add_micro(&fw->tx, "start", t->start_us);
    fw_send_frame(fw);
    int64_t end = t->start_us + trial_duration_us(t);
    if (fw->cfg.virtual_time) {
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
