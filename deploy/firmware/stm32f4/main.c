/*
 * clothd-fw on the STM32F405: the board set up, the core initialised, then fw_poll() forever, sleeping
 * between interrupts when no byte waits.
 */
#include <stdint.h>

#include "board.h"
#include "firmware.h"
#include "hal.h"

/* Several kilobytes (two frame buffers and every module's state): static, never on the 128 KB SRAM's
 * stack. */
static fw_state fw;

/* Sleep until the next interrupt (a received byte, or the 1 ms tick that advances the ramps and the
 * watchdog), unless bytes already wait. Interrupts are masked around the check so a byte landing between
 * the check and the wfi cannot be slept through: wfi still wakes on an interrupt that is pending while
 * masked, and it is taken as soon as they are unmasked. */
static void wait_for_interrupt_unless_bytes_wait(void)
{
    __asm__ volatile("cpsid i" ::: "memory");
    if (!board_serial_pending()) {
        __asm__ volatile("wfi");
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
        fw_poll(&fw);
        wait_for_interrupt_unless_bytes_wait();
    }
}
