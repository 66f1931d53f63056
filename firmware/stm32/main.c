/* STM32 board main loop: one context runs the core; interrupts only move bytes and ticks. */
#include "../core/board.h"
#include "../core/fw.h"
#include "regs.h"
#include "stm32.h"

/* The rig's reference limits (protocols/devices/default.yaml): EV 5 V, MV 10 V peak at the
 * amplifier inputs. A rig with other amplifiers rebuilds with -DLIMIT_EV_UV=... */
#ifndef LIMIT_EV_UV
#define LIMIT_EV_UV 5000000LL
#endif
#ifndef LIMIT_MV_UV
#define LIMIT_MV_UV 10000000LL
#endif
#ifndef WATCHDOG_MS
#define WATCHDOG_MS 500u
#endif
#ifndef SERIAL_NUMBER
#define SERIAL_NUMBER "ML-0001"
#endif

static fw_t fw;

static const fw_config_t config = {
    .limit_uv = {LIMIT_EV_UV, LIMIT_MV_UV},
    .wd_ms = WATCHDOG_MS,
    .fs_hz = 20000u,
    .ramp_us = 10000u,
    .jitter_us = 50u,
    .seed = 0u,
    .virtual_time = false,
    .fw_version = FW_VERSION BOARD_FW_SUFFIX,
    .model = "ML-FW-2CH",
    .serial_number = SERIAL_NUMBER,
};

int main(void)
{
    clock_init();
    hw_watchdog_init();
    interlock_init();
    output_init(&fw);
    usart_init();
    fw_init(&fw, &config, interlock_read_open());
    output_init(&fw); /* restart the sample stream against the initialised core */
    fw_boot(&fw);
    for (;;) {
        hw_watchdog_feed();
        uint8_t buf[64];
        size_t n = usart_read(buf, sizeof buf);
        if (n) {
            fw_rx(&fw, buf, n);
        }
        fw_set_interlock(&fw, interlock_read_open());
        fw_poll(&fw);
        output_service(&fw);
        usart_pump();
        if (!n && !output_active(&fw) && !usart_rx_pending()) {
            wait_for_interrupt(); /* SysTick wakes us every ms: the watchdog keeps its pace */
        }
    }
}
