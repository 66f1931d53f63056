/* Device state, safety rules and timing. The command handlers are in commands.c. */
#include "fw_internal.h"

#include <math.h>
#include <string.h>

#include "board.h"
#include "clock.h"
#include "fixed.h"

/* Recompute each channel's code limit for its attenuator step (after any step change). */
void fw_apply_attenuators(fw_t *fw)
{
    for (int ch = 0; ch < CH_COUNT; ch++) {
        uint8_t att = fw->cfg.att_db[fw->att_idx[ch]];
        fw->peak_code[ch] = 0; /* codes of another step are not comparable */
        int64_t lim = level_code_limit(&fw->conv[ch], fw->cfg.limit_uv[ch], att);
        /* behind an attenuator the voltage limit allows more codes than the output stage
         * plays linearly: the linear range caps it, so nothing is ever clipped */
        fw->code_limit[ch] = lim < fw->cfg.lin_code[ch] ? lim : fw->cfg.lin_code[ch];
        /* V at the amplifier input per code: 2 fsv / 2^bits / 10^(att/20) */
        float lsb = (float)fw->conv[ch].fsv_uv * 2.0f / 1e6f / (float)(1u << fw->conv[ch].bits);
        fw->v_per_code[ch] = lsb / powf(10.0f, (float)att / 20.0f);
        board_set_attenuator(ch, fw->att_idx[ch]);
    }
}

void fw_init(fw_t *fw, const fw_config_t *cfg, bool interlock_open)
{
    memset(fw, 0, sizeof *fw);
    fw->cfg = *cfg;
    /* v2 defaults: a 12-bit converter over ±10 V, no attenuator */
    for (int ch = 0; ch < CH_COUNT; ch++) {
        if (!fw->cfg.bits[ch] || fw->cfg.bits[ch] > LEVEL_MAX_BITS) {
            fw->cfg.bits[ch] = 12;
        }
        if (fw->cfg.fsv_uv[ch] <= 0) {
            fw->cfg.fsv_uv[ch] = 10 * FX_ONE;
        }
        fw->conv[ch].bits = fw->cfg.bits[ch];
        int64_t top = ((int64_t)1 << (fw->cfg.bits[ch] - 1)) - 1;
        if (fw->cfg.lin_code[ch] <= 0 || fw->cfg.lin_code[ch] > top) {
            fw->cfg.lin_code[ch] = level_default_linear(fw->cfg.bits[ch]);
        }
        fw->conv[ch].fsv_uv = fw->cfg.fsv_uv[ch];
    }
    if (fw->cfg.n_att == 0 || fw->cfg.n_att > LEVEL_MAX_STEPS) {
        fw->cfg.n_att = 1;
        fw->cfg.att_db[0] = 0;
    }
    if (!fw->cfg.build) {
        fw->cfg.build = FW_BUILD;
    }
    fw->interlock_open = interlock_open;
    fw_apply_attenuators(fw);
    fw->last_rx_mono_us = clock_now_us();
    prng_seed(&fw->prng, cfg->seed);
    line_rx_reset(&fw->rx);
    board_outputs_zero();
}

int64_t fw_now_us(const fw_t *fw)
{
    return fw->cfg.virtual_time ? fw->vt_us : (int64_t)clock_now_us();
}

void fw_send_frame(fw_t *fw)
{
    size_t n = frame_finish(&fw->tx);
    if (!n) {
        /* Never drop a frame silently: a host waiting for a reply would see a dead board. */
        if (fw->tx.reply) {
            frame_begin_reply(&fw->tx, fw->tx.seq, false);
            frame_add_text(&fw->tx, "SIZE");
            frame_add_text(&fw->tx, FW_SIZE_TEXT);
        } else {
            fw->event_no = (uint16_t)(fw->event_no + 1u);
            frame_begin_event(&fw->tx, fw->event_no, "FAULT");
            frame_add_str(&fw->tx, "code", "SIZE");
        }
        n = frame_finish(&fw->tx);
    }
    board_tx(fw->tx.buf, n);
}

void fw_begin_event(fw_t *fw, const char *name)
{
    fw->event_no = (uint16_t)(fw->event_no + 1u); /* wraps 65535 -> 0 like sequence numbers */
    frame_begin_event(&fw->tx, fw->event_no, name);
}

void fw_boot(fw_t *fw)
{
    fw_begin_event(fw, "BOOT");
    frame_add_str(&fw->tx, "fw", fw->cfg.fw_version);
    frame_add_str(&fw->tx, "rst", board_reset_cause());
    fw_send_frame(fw);
}

void fw_zero(fw_t *fw, const char *aborted_why)
{
    /* Silence the hardware first: the report can wait, the participant cannot. */
    board_outputs_zero();
    if (fw->playing && aborted_why) {
        fw_begin_event(fw, "ABORTED");
        frame_add_int(&fw->tx, "seq", fw->trial.seq);
        frame_add_str(&fw->tx, "why", aborted_why);
        fw_send_frame(fw);
    }
    fw->playing = false;
    for (int ch = 0; ch < CH_COUNT; ch++) {
        fw->stream[ch].active = false;
        fw->amp_uv[ch] = 0;
        fw->out_code[ch] = 0;
    }
}

void fw_err(fw_t *fw, uint16_t seq, const char *code, const char *text)
{
    fw_zero(fw, code);
    frame_begin_reply(&fw->tx, seq, false);
    frame_add_text(&fw->tx, code);
    frame_add_text(&fw->tx, text);
    fw_send_frame(fw);
}

void fw_send_done(fw_t *fw, int64_t end_us)
{
    const trial_t *t = &fw->trial;
    fw_begin_event(fw, "DONE");
    frame_add_int(&fw->tx, "seq", t->seq);
    frame_add_micro_list(&fw->tx, "on", t->actual_us, t->n);
    frame_add_micro(&fw->tx, "end", end_us);
    frame_add_micro(&fw->tx, "tamp", t->target.played_uv);
    frame_add_micro(&fw->tx, "mamp", t->masker.ch >= 0 ? t->masker.played_uv : 0);
    fw_send_frame(fw);
}

static void fault_frame(fw_t *fw)
{
    /* Garbage: its sequence number cannot be trusted, so no reply, an event instead. */
    fw->faults++;
    fw_zero(fw, "FRAME");
    fw_begin_event(fw, "FAULT");
    frame_add_str(&fw->tx, "code", "FRAME");
    fw_send_frame(fw);
}

void fw_rx(fw_t *fw, const uint8_t *data, size_t len)
{
    for (size_t i = 0; i < len; i++) {
        line_status_t st = line_rx_push(&fw->rx, data[i]);
        if (st == LINE_OVERFLOW) {
            fault_frame(fw);
        } else if (st == LINE_READY) {
            const char *bad = frame_decode_command(fw->rx.buf, fw->rx.len, &fw->cmd);
            line_rx_reset(&fw->rx);
            if (bad) {
                fault_frame(fw);
            } else {
                uint64_t t0 = clock_now_us();
                fw->last_rx_mono_us = t0; /* any valid command feeds the watchdog */
                fw_dispatch(fw, &fw->cmd);
                uint64_t took = clock_since_us(clock_now_us(), t0);
                fw->handler_max_us = took > fw->handler_max_us ? took : fw->handler_max_us;
            }
        }
    }
}

static bool armed(const fw_t *fw)
{
    return fw->playing || fw->amp_uv[CH_EV] > 0 || fw->amp_uv[CH_MV] > 0;
}

static void step_trial(fw_t *fw, int64_t now)
{
    trial_t *t = &fw->trial;
    while (fw->playing && t->step < 2 * t->n && trial_step_time(t, t->step) <= now) {
        int k = t->step / 2;
        if (t->step % 2 == 0) {
            if (k + 1 == t->ti) {
                fw->amp_uv[t->target.ch] += t->target.played_uv;
            }
            if (t->masker.ch >= 0) {
                fw->amp_uv[t->masker.ch] += t->masker.played_uv;
            }
            if (!t->onset_seen[k]) {
                t->actual_us[k] = now; /* no output stage rendered it (yet): when noticed */
            }
        } else {
            fw->amp_uv[CH_EV] = fw->amp_uv[CH_MV] = 0;
        }
        t->step++;
        if (t->step == 2 * t->n) {
            fw->playing = false;
            fw_send_done(fw, now);
        }
    }
}

void fw_limit_fault(fw_t *fw)
{
    if (!fw->limit_tripped) {
        return;
    }
    /* the output stage met a sample over its limit and already played 0 instead */
    fw->limit_tripped = false;
    fw->faults++;
    fw_zero(fw, "LIMIT");
    fw_begin_event(fw, "FAULT");
    frame_add_str(&fw->tx, "code", "LIMIT");
    fw_send_frame(fw);
}

static void poll_work(fw_t *fw);

void fw_refill_end(fw_t *fw)
{
    if (fw->render_open) { /* the output stage's refill has ended: record its work */
        uint64_t took = clock_since_us(clock_now_us(), fw->render_t0_us);
        fw->refill_max_us = took > fw->refill_max_us ? took : fw->refill_max_us;
        fw->render_open = false;
    }
}

void fw_poll(fw_t *fw)
{
    /* A board that does not call fw_refill_end() gets its refill closed here (the measure then
     * includes whatever ran between, e.g. a sleep until the next interrupt). */
    fw_refill_end(fw);
    uint64_t t0 = clock_now_us();
    poll_work(fw);
    uint64_t took = clock_since_us(clock_now_us(), t0);
    fw->poll_max_us = took > fw->poll_max_us ? took : fw->poll_max_us;
}

static void poll_work(fw_t *fw)
{
    board_iwdg_feed();
    fw_limit_fault(fw);
    uint64_t mono = clock_now_us();
    if (fw->playing && !fw->cfg.virtual_time) {
        step_trial(fw, fw_now_us(fw));
    }
    if (fw->cfg.wd_ms && armed(fw)) {
        uint64_t quiet = clock_since_us(mono, fw->last_rx_mono_us);
        if (quiet > (uint64_t)fw->cfg.wd_ms * 1000u) {
            fw->wd_trips++;
            fw_zero(fw, "WATCHDOG");
            fw_begin_event(fw, "WATCHDOG");
            frame_add_int(&fw->tx, "quiet_ms", (int64_t)((quiet + 500u) / 1000u));
            fw_send_frame(fw);
        }
    }
}

uint64_t fw_next_due(const fw_t *fw)
{
    uint64_t due = UINT64_MAX;
    if (fw->playing && !fw->cfg.virtual_time && fw->trial.step < 2 * fw->trial.n) {
        int64_t t = trial_step_time(&fw->trial, fw->trial.step);
        due = t > 0 ? (uint64_t)t : 0;
    }
    if (fw->limit_tripped) {
        return 0;
    }
    if (fw->cfg.wd_ms && armed(fw)) {
        uint64_t wd = fw->last_rx_mono_us + (uint64_t)fw->cfg.wd_ms * 1000u + 1u;
        due = wd < due ? wd : due;
    }
    return due;
}

void fw_set_interlock(fw_t *fw, bool open)
{
    if (open == fw->interlock_open) {
        return;
    }
    fw->interlock_open = open;
    if (open) {
        fw_zero(fw, "INTERLOCK");
    }
    fw_begin_event(fw, "INTERLOCK");
    frame_add_str(&fw->tx, "state", open ? "open" : "closed");
    fw_send_frame(fw);
}

void fw_link_lost(fw_t *fw)
{
    fw_zero(fw, NULL);
}

static void render(fw_t *fw, int64_t t_us, float out[CH_COUNT]);

void fw_render(fw_t *fw, int64_t t_us, float out[CH_COUNT])
{
    if (!fw->render_open) { /* the first sample of this main-loop iteration's refill */
        fw->render_open = true;
        fw->render_t0_us = clock_now_us();
    }
    fw->render_samples++;
    render(fw, t_us, out);
}

static void render(fw_t *fw, int64_t t_us, float out[CH_COUNT])
{
    float code[CH_COUNT] = {0.0f, 0.0f};
    out[CH_EV] = out[CH_MV] = 0.0f;
    fw->out_code[CH_EV] = fw->out_code[CH_MV] = 0;
    if (fw->interlock_open || fw->limit_tripped) {
        return;
    }
    if (fw->playing) {
        trial_render(&fw->trial, t_us, fw->cfg.fs_hz, code);
    } else {
        for (int ch = 0; ch < CH_COUNT; ch++) {
            const stream_t *s = &fw->stream[ch];
            if (s->active && fw->amp_uv[ch] > 0) {
                uint32_t i = us_to_samples(t_us - s->t0_us, fw->cfg.fs_hz);
                code[ch] = tone_code(&s->tone, i, s->code_amp);
            }
        }
    }
    if (fw->cfg.test_overdrive_pct) {
        for (int ch = 0; ch < CH_COUNT; ch++) {
            code[ch] *= (float)fw->cfg.test_overdrive_pct / 100.0f;
        }
    }
    int32_t c[CH_COUNT];
    for (int ch = 0; ch < CH_COUNT; ch++) {
        /* the limit check before the output stage: not clipped, refused (NaN fails too) */
        float lim = (float)fw->code_limit[ch] + 0.5f;
        if (!(fabsf(code[ch]) < lim)) {
            fw->limit_tripped = true;
            board_outputs_zero();
            return;
        }
        c[ch] = (int32_t)lrintf(code[ch]);
    }
    for (int ch = 0; ch < CH_COUNT; ch++) {
        fw->out_code[ch] = c[ch];
        out[ch] = (float)c[ch] * fw->v_per_code[ch];
        int64_t mag = c[ch] < 0 ? -(int64_t)c[ch] : c[ch];
        if (mag > fw->peak_code[ch]) { /* exact µV only when a new largest code appears */
            fw->peak_code[ch] = mag;
            int64_t uv = level_played_uv(&fw->conv[ch], mag, fw->cfg.att_db[fw->att_idx[ch]]);
            fw->peak_uv[ch] = uv > fw->peak_uv[ch] ? uv : fw->peak_uv[ch];
        }
    }
}
