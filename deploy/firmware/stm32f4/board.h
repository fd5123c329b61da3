/*
 * The STM32F405 board layer under hal.h: clocks, the 1 kHz SysTick, USART1 with an interrupt-fed
 * receive ring, the drivers' ENABLE line, the e-stop input, and the steppers (steppers.c). The handlers are referenced from startup.c's vector table.
 */
#ifndef CLOTHD_FW_STM32F4_BOARD_H
#define CLOTHD_FW_STM32F4_BOARD_H

#include <stdbool.h>
#include <stdint.h>

/* Modules this controller drives (HELLO_ACK reports it); hwsim's default table has 48. */
#ifndef BOARD_MODULES
#define BOARD_MODULES 48
#endif

/* Modules with STEP/DIR pins (steppers.c): 4 (8 drivers) at most on the reference pin map. */
#ifndef BOARD_STEP_MODULES
#define BOARD_STEP_MODULES 4
#endif

/* SysTick's rate: the step tick (steppers.c), which also wakes the main loop. 40 kHz on a board (up to
 * 20,000 steps/s); 10 kHz in the emulator build (up to 5,000 steps/s, higher rates clipped and counted):
 * QEMU spends most of a host core on 40,000 timer interrupts a second, which starved its USART on a
 * loaded machine (an ESTOP's ACK 2.2 s late behind queued COMMANDs). */
#ifndef STEP_TICK_HZ
#if defined(BOARD_CLOCKS_QEMU)
#define STEP_TICK_HZ 10000u
#else
#define STEP_TICK_HZ 40000u
#endif
#endif

/* Set up the clocks, the pins, the USART and the SysTick; the drivers stay disabled. */
void board_init(void);

/* The main loop's wake-up: true while received bytes wait in the ring, an e-stop edge is unseen, or a
 * millisecond of ticks has passed since board_polling() (called as a poll starts). The main loop sleeps
 * through the other step ticks: a poll per millisecond is all the core needs. */
bool board_work_pending(void);
void board_polling(void);

/* Cut the drivers' ENABLE line: what the fault handlers do before they halt. */
void board_drivers_off(void);

void board_systick_handler(void);
void board_usart1_handler(void);
void board_exti1_handler(void); /* the hardware e-stop input (PA1) */

/* steppers.c: the STEP/DIR pins set up; one step tick (from SysTick's interrupt); stepping on or off
 * (off: the steps owed are dropped, as the drivers are disabled). */
void steppers_init(void);
void steppers_tick(void);
void steppers_enable(bool enabled);

#endif
