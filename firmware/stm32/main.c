/* STM32 board main loop: one context runs the core; interrupts only move bytes and ticks. */
#include "../core/board.h"
#include "../core/fw.h"
#include "board_logic.h"
#include "regs.h"
#include "stm32.h"

/* The rig's limits, watchdog, serial number, converter full scale and attenuator steps come
 * from the Makefile (make LIMIT_EV_UV=... LIMIT_MV_UV=...; defaults in stm32.h: the reference
 * rig of protocols/devices/default.yaml). A limit outside the DAC buffer's linear range could
 * only be met by clipping: such a build fails here instead. */
_Static_assert(LIMIT_EV_UV > 0 && LIMIT_EV_UV * 2048LL <= FSV_EV_UV * 1798LL,
               "LIMIT_EV_UV exceeds the linear range of the EV output (FSV_EV_UV * 1798/2048)");
_Static_assert(DAC_SPAN == LEVEL_REF_LINEAR_CODES && DAC_BITS == 12,
               "the core's reference linear range is this DAC's");
_Static_assert(LIMIT_MV_UV > 0 && LIMIT_MV_UV * 2048LL <= FSV_MV_UV * 1798LL,
               "LIMIT_MV_UV exceeds the linear range of the MV output (FSV_MV_UV * 1798/2048)");

/* The build identity and rig options, kept in the image for `strings`/gdb and the build test. */
__attribute__((used)) const char board_build_info[] =
    "masking-fw build=" FW_BUILD " sn=" SERIAL_NUMBER " att=" ATT_STEPS_DB;

static fw_t fw;

volatile uint32_t dac_clamped; /* samples outside the DAC's linear range (gdb; 0 when fine) */

#if FW_PROTOCOL_VERSION >= 2
bool board_codes_playable(fw_t *f)
{
    if (dac_code_linear(f->out_code[0]) && dac_code_linear(f->out_code[1])) {
        return true;
    }
    /* Beyond the buffer's linear range: cannot happen since the core's code limits are
     * capped by cfg.lin_code (= DAC_SPAN), so this is a second line of defence. Play 0 V and
     * let the core report it as a sample over the limit, FAULT code=LIMIT, rather than clip.
     * QEMU stands in for the DAC board and applies the same rule. */
    dac_clamped++;
    f->limit_tripped = true;
    board_outputs_zero();
    return false;
}
#endif

static fw_config_t config = {
    .limit_uv = {LIMIT_EV_UV, LIMIT_MV_UV},
    .wd_ms = WATCHDOG_MS,
    .fs_hz = 20000u,
    .ramp_us = 10000u,
    .jitter_us = 50u,
    .seed = 0u,
    .virtual_time = false,
    .fw_version = FW_VERSION, /* exactly fw-X.Y.Z: the host parses it */
    .model = BOARD_MODEL,
    .serial_number = SERIAL_NUMBER,
#if FW_PROTOCOL_VERSION >= 2
    .bits = {DAC_BITS, DAC_BITS},
    .fsv_uv = {FSV_EV_UV, FSV_MV_UV},
    /* the DAC buffer's linear range: the core caps every code limit by it, so a level the
     * buffer would clip is refused at the command (ERR LIMIT) on every implementation alike */
    .lin_code = {DAC_SPAN, DAC_SPAN},
    .build = FW_BUILD,
#endif
};

static void config_attenuators(void)
{
#if FW_PROTOCOL_VERSION >= 2
    uint8_t steps[ATT_MAX_STEPS];
    unsigned n = att_parse(ATT_STEPS_DB, steps); /* the Makefile checked the list */
    for (unsigned i = 0; i < n && i < LEVEL_MAX_STEPS; i++) {
        config.att_db[i] = steps[i];
    }
    config.n_att = (uint8_t)(n < LEVEL_MAX_STEPS ? n : LEVEL_MAX_STEPS);
#endif
}

int main(void)
{
    reset_cause_capture(); /* before anything could reset again */
    __asm__ volatile("" ::"r"(board_build_info)); /* keep it through --gc-sections */
    clock_init();
    hw_watchdog_init();
    attenuator_init();
    config_attenuators();
    interlock_init();
    output_init(&fw);
    usart_init();
    fw_init(&fw, &config, interlock_read_open());
    output_init(&fw); /* restart the sample stream against the initialised core */
    fw_boot(&fw);
    for (;;) {
        board_iwdg_feed();
        uint8_t buf[64];
        size_t n = usart_read(buf, sizeof buf);
        if (n) {
            fw_rx(&fw, buf, n);
        }
        fw_set_interlock(&fw, interlock_read_open());
        fw_poll(&fw);
        output_service(&fw);
        usart_pump();
        if (!n && !usart_rx_pending()) {
            /* Sleep until the next interrupt, also while playing: SysTick wakes us every ms,
             * which keeps the watchdog's pace and the DMA buffer's 10 ms lead (and under QEMU
             * keeps a busy loop from racing the -icount virtual clock ahead of real time). */
            wait_for_interrupt();
        }
    }
}
