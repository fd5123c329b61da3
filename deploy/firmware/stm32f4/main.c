/*
 * clothd-fw on the STM32F405: the board set up, the core initialised, then fw_poll() forever, sleeping
 * until a byte, an e-stop edge or the next millisecond.
 */
#include <stdint.h>

#include "board.h"
#include "firmware.h"
#include "hal.h"

/* Several kilobytes (two frame buffers and every module's state): static, never on the 128 KB SRAM's
 * stack. */
static fw_state fw;

/* Sleep until there is work: a received byte, an e-stop edge, or the next millisecond (the ramps and the
 * watchdog advance then). The step tick interrupts 40 times a millisecond; between polls the loop goes
 * back to sleep after each. Interrupts are masked around the check so an interrupt landing between the
 * check and the wfi cannot be slept through: wfi still wakes on an interrupt that is pending while
 * masked, and it is taken as soon as they are unmasked. */
static void wait_for_work(void)
{
    __asm__ volatile("cpsid i" ::: "memory");
    while (!board_work_pending()) {
        __asm__ volatile("wfi");
        __asm__ volatile("cpsie i" ::: "memory"); /* the pending interrupt is taken here */
        __asm__ volatile("cpsid i" ::: "memory");
    }
    __asm__ volatile("cpsie i" ::: "memory");
}

int main(void)
{
    board_init();
    fw_config config = fw_default_config(BOARD_MODULES);
    if (!fw_init(&fw, &config, hal_now_ms())) {
        board_drivers_off();
        /* A configuration out of range is a build error: stay silent, the host sees no HELLO_ACK. */
        for (;;) {
            __asm__ volatile("wfi");
        }
    }
    for (;;) {
        board_polling();
        fw_poll(&fw);
        wait_for_work();
    }
}
