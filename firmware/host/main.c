/* Host board: the firmware core on a POSIX pseudo-terminal with a simulated two-channel DAC.
 *
 * The first line of stdout is the pty slave path (connect with --device serial:PATH). The
 * simulated DAC is fed sample by sample at the configured rate from the same render function
 * the STM32 DMA buffer uses; DIAG reports its last samples. The interlock input is a signal:
 * SIGUSR1 opens it, SIGUSR2 closes it (or --interlock-open at start). SIGTERM/SIGINT/SIGHUP
 * zero the outputs and exit 0.
 *
 * The independent watchdog is modelled like the board's IWDG: the core feeds it once per
 * main-loop iteration (fw_poll); an iteration whose work (CPU time of this process, so a
 * loaded machine does not trip it) exceeds --iwdg-ms resets the device: outputs zeroed, the
 * core re-initialised, "!n BOOT ... rst=watchdog" sent, as a starved board would. */
#define _XOPEN_SOURCE 700
#define _DEFAULT_SOURCE

#include <errno.h>
#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include "../core/board.h"
#include "../core/fixed.h"
#include "../core/fw.h"

static fw_t fw;
static int master_fd = -1;
static struct timespec t_boot;

/* simulated DAC */
static float dac_last[CH_COUNT];
static uint64_t dac_next_sample; /* index of the next sample to output (since boot) */
static uint64_t dac_samples_out;

/* outgoing bytes the pty could not take yet */
static char out_buf[1 << 16];
static size_t out_len;

static volatile sig_atomic_t want_exit, il_request = -1;

/* modelled IWDG and reset cause */
static const char *reset_cause = "power";
static uint32_t iwdg_ms = 100;
static uint64_t iwdg_fed_cpu_us;
static uint32_t test_stall_ms; /* fault injection: burn this much CPU once a trial starts */
static uint64_t micros_offset; /* --clock-start-us: start the 32-bit counter near its wrap */
static uint32_t stepback_us;   /* --test-clock-stepback-us: a counter that glitches back */

uint32_t board_micros32(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    uint64_t us = (uint64_t)(ts.tv_sec - t_boot.tv_sec) * 1000000u +
                  (uint64_t)((ts.tv_nsec - t_boot.tv_nsec) / 1000);
    if (stepback_us && (us / 250000u) % 2u == 1u) {
        us -= stepback_us; /* fault injection: every other 250 ms the read is late-latched */
    }
    return (uint32_t)(us + micros_offset); /* wraps like a 32-bit timer */
}

const char *board_reset_cause(void)
{
    return reset_cause;
}

const char *board_clock_source(void)
{
    return "host";
}

void board_set_attenuator(int ch, uint8_t step_index)
{
    (void)ch;
    (void)step_index; /* the simulated DAC reports volts at the amplifier input directly */
}

static uint64_t cpu_us(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
    return (uint64_t)ts.tv_sec * 1000000u + (uint64_t)ts.tv_nsec / 1000u;
}

void board_iwdg_feed(void)
{
    iwdg_fed_cpu_us = cpu_us();
}

static void burn_cpu_ms(uint32_t ms)
{
    uint64_t until = cpu_us() + (uint64_t)ms * 1000u;
    while (cpu_us() < until) {
    }
}

static void flush_out(void)
{
    while (out_len > 0) {
        ssize_t n = write(master_fd, out_buf, out_len);
        if (n <= 0) {
            return; /* EAGAIN: the client is not reading; retry in the loop */
        }
        memmove(out_buf, out_buf + n, out_len - (size_t)n);
        out_len -= (size_t)n;
    }
}

void board_tx(const char *data, size_t len)
{
    if (out_len + len > sizeof out_buf) {
        return; /* nobody is reading: drop rather than stall the firmware loop */
    }
    memcpy(out_buf + out_len, data, len);
    out_len += len;
    flush_out();
}

static uint64_t sample_now(void)
{
    return board_mono_us() * fw.cfg.fs_hz / 1000000u;
}

void board_outputs_zero(void)
{
    dac_last[CH_EV] = dac_last[CH_MV] = 0.0f;
    if (fw.cfg.fs_hz) {
        dac_next_sample = sample_now() + 1; /* nothing queued survives a zeroing */
    }
}

void board_dac_last(float out[2])
{
    out[0] = dac_last[CH_EV];
    out[1] = dac_last[CH_MV];
}

static void run_dac(void)
{
    uint64_t now = sample_now();
    if (now < dac_next_sample) {
        return; /* (an unsigned now - next here wrapped and skipped the first second) */
    }
    if (now - dac_next_sample > fw.cfg.fs_hz) { /* stalled > 1 s (debugger): skip ahead */
        dac_next_sample = now - fw.cfg.fs_hz;
    }
    for (; dac_next_sample <= now; dac_next_sample++) {
        int64_t t_us = (int64_t)(dac_next_sample * 1000000u / fw.cfg.fs_hz);
        fw_render(&fw, t_us, dac_last);
        dac_samples_out++;
    }
    fw_refill_end(&fw);
}

static void on_signal(int sig)
{
    if (sig == SIGUSR1) {
        il_request = 1;
    } else if (sig == SIGUSR2) {
        il_request = 0;
    } else {
        want_exit = 1;
    }
}

static void usage(const char *argv0)
{
    fprintf(stderr,
            "usage: %s [--virtual-time] [--wd-ms N] [--max-ev V] [--max-mv V] [--fs HZ]\n"
            "          [--ramp-us N] [--jitter-us N] [--seed N] [--sn TEXT] [--model TEXT]\n"
            "          [--interlock-open] [--bits-ev N] [--bits-mv N] [--fsv-ev V]\n"
            "          [--fsv-mv V] [--att DB,DB,..] [--lin-ev N] [--lin-mv N]\n"
            "          [--iwdg-ms N] [--vt-render] [--check-hello]\n"
            "  test-only fault injection: [--test-overdrive-pct P] [--test-stall-ms N]\n"
            "          [--clock-start-us N] [--test-clock-stepback-us N]\n"
            "Serves the masking-lab device protocol on a new pseudo-terminal; prints its path.\n"
            "SIGUSR1 opens the interlock, SIGUSR2 closes it; SIGTERM zeroes and exits.\n",
            argv0);
}

static int64_t parse_micro(const char *opt, const char *text);

/* "0,20,40": ascending whole dB steps 0..60, the first 0 */
static void parse_att(fw_config_t *cfg, const char *text)
{
    char buf[64];
    size_t len = strlen(text);
    if (len >= sizeof buf) {
        len = sizeof buf - 1;
    }
    memcpy(buf, text, len);
    buf[len] = '\0';
    cfg->n_att = 0;
    for (char *tok = strtok(buf, ","); tok; tok = strtok(NULL, ",")) {
        int64_t v = parse_micro("--att", tok);
        int64_t prev = cfg->n_att ? cfg->att_db[cfg->n_att - 1] : -1;
        if (cfg->n_att == LEVEL_MAX_STEPS || v % 1000000 || v / 1000000 > LEVEL_MAX_ATT_DB ||
            v / 1000000 <= prev || (cfg->n_att == 0 && v != 0)) {
            fprintf(stderr, "masking-fw: --att needs up to %d ascending whole dB steps in "
                            "0..%d starting at 0, got '%s'\n",
                    LEVEL_MAX_STEPS, LEVEL_MAX_ATT_DB, text);
            exit(2);
        }
        cfg->att_db[cfg->n_att++] = (uint8_t)(v / 1000000);
    }
}

static int64_t parse_micro(const char *opt, const char *text)
{
    int64_t v;
    if (!fx_parse(text, &v)) {
        fprintf(stderr, "masking-fw: %s needs a decimal number, got '%s'\n", opt, text);
        exit(2);
    }
    return v;
}

int main(int argc, char **argv)
{
    fw_config_t cfg = {
        .limit_uv = {5 * 1000000LL, 10 * 1000000LL},
        .wd_ms = 500,
        .fs_hz = 20000,
        .ramp_us = 10000,
        .jitter_us = 50,
        .seed = 0,
        .virtual_time = false,
        .fw_version = FW_VERSION,
        .bits = {12, 12},
        .fsv_uv = {10 * 1000000LL, 10 * 1000000LL},
        .att_db = {0, 20, 40},
        .n_att = 3,
        .model = "ML-FW-2CH",
        .serial_number = "HOST-0001",
    };
    bool il_open = false;
    bool check_hello = false;
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i];
        const char *v = (i + 1 < argc) ? argv[i + 1] : NULL;
        if (strcmp(a, "--virtual-time") == 0) {
            cfg.virtual_time = true;
        } else if (strcmp(a, "--vt-render") == 0) {
            cfg.vt_render = true;
        } else if (strcmp(a, "--interlock-open") == 0) {
            il_open = true;
        } else if (strcmp(a, "--check-hello") == 0) {
            check_hello = true;
        } else if (strcmp(a, "-h") == 0 || strcmp(a, "--help") == 0) {
            usage(argv[0]);
            return 0;
        } else if (!v) {
            usage(argv[0]);
            return 2;
        } else {
            i++;
            if (strcmp(a, "--wd-ms") == 0) {
                cfg.wd_ms = (uint32_t)(parse_micro(a, v) / 1000000);
            } else if (strcmp(a, "--max-ev") == 0) {
                cfg.limit_uv[CH_EV] = parse_micro(a, v);
            } else if (strcmp(a, "--max-mv") == 0) {
                cfg.limit_uv[CH_MV] = parse_micro(a, v);
            } else if (strcmp(a, "--fs") == 0) {
                cfg.fs_hz = (uint32_t)(parse_micro(a, v) / 1000000);
            } else if (strcmp(a, "--ramp-us") == 0) {
                cfg.ramp_us = (uint32_t)(parse_micro(a, v) / 1000000);
            } else if (strcmp(a, "--jitter-us") == 0) {
                cfg.jitter_us = (uint32_t)(parse_micro(a, v) / 1000000);
            } else if (strcmp(a, "--seed") == 0) {
                cfg.seed = (uint32_t)(int64_t)(parse_micro(a, v) / 1000000); /* mod 2^32 */
            } else if (strcmp(a, "--bits-ev") == 0 || strcmp(a, "--bits-mv") == 0) {
                int64_t b = parse_micro(a, v) / 1000000;
                cfg.bits[a[7] == 'e' ? 0 : 1] = (uint8_t)(b >= 2 && b <= LEVEL_MAX_BITS ? b : 0);
                if (b < 2 || b > LEVEL_MAX_BITS) {
                    fprintf(stderr, "masking-fw: %s needs 2..%d bits\n", a, LEVEL_MAX_BITS);
                    return 2;
                }
            } else if (strcmp(a, "--fsv-ev") == 0) {
                cfg.fsv_uv[0] = parse_micro(a, v);
            } else if (strcmp(a, "--fsv-mv") == 0) {
                cfg.fsv_uv[1] = parse_micro(a, v);
            } else if (strcmp(a, "--lin-ev") == 0 || strcmp(a, "--lin-mv") == 0) {
                int64_t n = parse_micro(a, v);
                if (n % 1000000 || n < 1000000 || n > 32767 * 1000000LL) {
                    fprintf(stderr, "masking-fw: %s needs a whole number of codes >= 1\n", a);
                    return 2;
                }
                cfg.lin_code[a[6] == 'e' ? 0 : 1] = n / 1000000;
            } else if (strcmp(a, "--att") == 0) {
                parse_att(&cfg, v);
            } else if (strcmp(a, "--iwdg-ms") == 0) {
                iwdg_ms = (uint32_t)(parse_micro(a, v) / 1000000);
            } else if (strcmp(a, "--test-overdrive-pct") == 0) {
                cfg.test_overdrive_pct = (uint32_t)(parse_micro(a, v) / 1000000);
            } else if (strcmp(a, "--test-stall-ms") == 0) {
                test_stall_ms = (uint32_t)(parse_micro(a, v) / 1000000);
            } else if (strcmp(a, "--test-clock-stepback-us") == 0) {
                stepback_us = (uint32_t)(parse_micro(a, v) / 1000000);
            } else if (strcmp(a, "--clock-start-us") == 0) {
                micros_offset = (uint64_t)(parse_micro(a, v) / 1000000);
            } else if (strcmp(a, "--sn") == 0) {
                cfg.serial_number = v;
            } else if (strcmp(a, "--model") == 0) {
                cfg.model = v;
            } else {
                usage(argv[0]);
                return 2;
            }
        }
    }
    bool bad_v = false;
    for (int ch = 0; ch < CH_COUNT; ch++) {
        bad_v |= cfg.limit_uv[ch] <= 0 || cfg.limit_uv[ch] > 1000 * 1000000LL;
        bad_v |= cfg.fsv_uv[ch] <= 0 || cfg.fsv_uv[ch] > 1000 * 1000000LL;
        int bits = cfg.bits[ch] ? cfg.bits[ch] : 12;
        if (cfg.lin_code[ch] > ((int64_t)1 << (bits - 1)) - 1) {
            fprintf(stderr, "masking-fw: --lin-%s %lld exceeds the %d-bit converter's %lld codes\n",
                    ch ? "mv" : "ev", (long long)cfg.lin_code[ch], bits,
                    (long long)(((int64_t)1 << (bits - 1)) - 1));
            return 2;
        }
    }
    if (cfg.fs_hz < 1000 || cfg.fs_hz > 1000000 || bad_v || iwdg_ms == 0) {
        fprintf(stderr, "masking-fw: need 1000 <= --fs <= 1000000, limits and full scales in "
                        "(0, 1000] V, --iwdg-ms > 0\n");
        return 2;
    }
    clock_gettime(CLOCK_MONOTONIC, &t_boot);
    if (check_hello) {
        /* The Makefile's build-time check of the STM32/QEMU options: HELLO with the longest
         * reset cause (8 characters; clk "host" is at least as long as "hse"/"hsi"). */
        reset_cause = "watchdog";
        fw_init(&fw, &cfg, il_open);
        bool fits = fw_hello_fits(&fw);
        if (!fits) {
            fprintf(stderr, "masking-fw: HELLO would exceed %d bytes with these options\n",
                    FRAME_MAX_BYTES);
        }
        return fits ? 0 : 2;
    }

    master_fd = posix_openpt(O_RDWR | O_NOCTTY);
    if (master_fd < 0 || grantpt(master_fd) || unlockpt(master_fd)) {
        perror("masking-fw: posix_openpt");
        return 1;
    }
    const char *slave_name = ptsname(master_fd);
    /* Hold the slave open ourselves: a client closing its end must not make the master
     * return EIO, and a raw slave neither echoes nor turns \n into \r\n. */
    int slave_fd = open(slave_name, O_RDWR | O_NOCTTY);
    struct termios tio;
    if (slave_fd < 0 || tcgetattr(slave_fd, &tio)) {
        perror("masking-fw: pty slave");
        return 1;
    }
    cfmakeraw(&tio);
    tcsetattr(slave_fd, TCSANOW, &tio);
    fcntl(master_fd, F_SETFL, fcntl(master_fd, F_GETFL) | O_NONBLOCK);

    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal;
    sigemptyset(&sa.sa_mask);
    int sigs[] = {SIGUSR1, SIGUSR2, SIGTERM, SIGINT, SIGHUP};
    for (size_t i = 0; i < sizeof sigs / sizeof sigs[0]; i++) {
        sigaction(sigs[i], &sa, NULL);
    }

    fw_init(&fw, &cfg, il_open);
    if (!fw_hello_fits(&fw)) {
        fprintf(stderr,
                "masking-fw: HELLO would exceed %d bytes with these options: shorten --sn "
                "(or --model, --att)\n",
                FRAME_MAX_BYTES);
        return 2;
    }
    printf("%s\n", slave_name);
    fflush(stdout);
    fprintf(stderr,
            "masking-fw %s on %s: %s time, limits EV %.6g V / MV %.6g V, watchdog %u ms, "
            "fs %u Hz, interlock %s\n",
            cfg.fw_version, slave_name, cfg.virtual_time ? "virtual" : "real",
            (double)cfg.limit_uv[0] / 1e6, (double)cfg.limit_uv[1] / 1e6, cfg.wd_ms, cfg.fs_hz,
            il_open ? "open" : "closed");
    fw_boot(&fw);
    board_iwdg_feed();

    while (!want_exit) {
        if (il_request >= 0) {
            fw_set_interlock(&fw, il_request == 1);
            il_request = -1;
        }
        int timeout_ms = 1; /* the DAC runs in 1 ms batches while anything may be output */
        bool active = fw.playing || fw.amp_uv[0] > 0 || fw.amp_uv[1] > 0;
        if (!active || fw.cfg.virtual_time) {
            uint64_t due = fw_next_due(&fw), now = board_mono_us();
            timeout_ms = due == UINT64_MAX ? 100 : (due <= now ? 0 : (int)((due - now) / 1000) + 1);
            timeout_ms = timeout_ms > 100 ? 100 : timeout_ms;
        }
        struct pollfd pfd = {master_fd, POLLIN | (out_len ? POLLOUT : 0), 0};
        int rc = poll(&pfd, 1, timeout_ms);
        if (rc < 0 && errno != EINTR) {
            perror("masking-fw: poll");
            break;
        }
        if (rc > 0 && (pfd.revents & POLLIN)) {
            uint8_t buf[512];
            ssize_t n = read(master_fd, buf, sizeof buf);
            if (n > 0) {
                fw_rx(&fw, buf, (size_t)n);
            }
        }
        if (test_stall_ms && fw.playing) {
            burn_cpu_ms(test_stall_ms); /* fault injection: one starved iteration */
            test_stall_ms = 0;
        }
        flush_out();
        if (!fw.cfg.virtual_time) {
            run_dac();
        }
        if (cpu_us() - iwdg_fed_cpu_us > (uint64_t)iwdg_ms * 1000u) {
            /* the modelled IWDG expired before this iteration fed it: reset */
            fprintf(stderr, "masking-fw: IWDG expired (iteration > %u ms): reset\n", iwdg_ms);
            reset_cause = "watchdog";
            fw_init(&fw, &cfg, fw.interlock_open);
            fw_boot(&fw);
            flush_out();
        }
        fw_poll(&fw);
    }
    fw_link_lost(&fw);
    fprintf(stderr, "masking-fw: stopped, outputs zeroed (%llu DAC samples output)\n",
            (unsigned long long)dac_samples_out);
    close(slave_fd);
    close(master_fd);
    return 0;
}
