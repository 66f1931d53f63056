/* Device state, safety rules and timing. The command handlers are in commands.c. */
#include "fw_internal.h"

#include <string.h>

#include "board.h"

void fw_init(fw_t *fw, const fw_config_t *cfg, bool interlock_open)
{
    memset(fw, 0, sizeof *fw);
    fw->cfg = *cfg;
    fw->interlock_open = interlock_open;
    fw->last_rx_mono_us = board_mono_us();
    prng_seed(&fw->prng, cfg->seed);
    line_rx_reset(&fw->rx);
    board_outputs_zero();
}

int64_t fw_now_us(const fw_t *fw)
{
    return fw->cfg.virtual_time ? fw->vt_us : (int64_t)board_mono_us();
}

void fw_send_frame(fw_t *fw)
{
    size_t n = frame_finish(&fw->tx);
    if (n) {
        board_tx(fw->tx.buf, n);
    }
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
    frame_add_micro(&fw->tx, "tamp", t->target.amp_uv);
    frame_add_micro(&fw->tx, "mamp", t->masker.ch >= 0 ? t->masker.amp_uv : 0);
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
                fw->last_rx_mono_us = board_mono_us(); /* any valid command feeds the watchdog */
                fw_dispatch(fw, &fw->cmd);
                /* A slow command (PLAY scans its tones) kept us from hearing the host: count
                 * the host as heard when we are ready to listen again. */
                fw->last_rx_mono_us = board_mono_us();
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
                fw->amp_uv[t->target.ch] += t->target.amp_uv;
            }
            if (t->masker.ch >= 0) {
                fw->amp_uv[t->masker.ch] += t->masker.amp_uv;
            }
            t->actual_us[k] = now;
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

void fw_poll(fw_t *fw)
{
    uint64_t mono = board_mono_us();
    if (fw->playing && !fw->cfg.virtual_time) {
        step_trial(fw, fw_now_us(fw));
    }
    if (fw->cfg.wd_ms && armed(fw)) {
        uint64_t quiet = mono - fw->last_rx_mono_us;
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

void fw_render(const fw_t *fw, int64_t t_us, float out[CH_COUNT])
{
    out[CH_EV] = out[CH_MV] = 0.0f;
    if (fw->interlock_open) {
        return;
    }
    if (fw->playing) {
        trial_render(&fw->trial, t_us, fw->cfg.fs_hz, out);
        return;
    }
    for (int ch = 0; ch < CH_COUNT; ch++) {
        const stream_t *s = &fw->stream[ch];
        if (s->active && fw->amp_uv[ch] > 0) {
            uint32_t i = us_to_samples(t_us - s->t0_us, fw->cfg.fs_hz);
            out[ch] = tone_unit(&s->tone, i) * ((float)fw->amp_uv[ch] / 1e6f);
        }
    }
}
