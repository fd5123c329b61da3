/*
 * The STM32F405 board layer under hal.h: clocks, the 1 kHz SysTick, USART1 with an interrupt-fed
 * receive ring, and the drivers' ENABLE line. The handlers are referenced from startup.c's vector table.
 */
#ifndef CLOTHD_FW_STM32F4_BOARD_H
#define CLOTHD_FW_STM32F4_BOARD_H

#include <stdbool.h>

/* Modules this controller drives (HELLO_ACK reports it); hwsim's default table has 48. */
#ifndef BOARD_MODULES
#define BOARD_MODULES 48
#endif

/* Set up the clocks, the pins, the USART and the SysTick; the drivers stay disabled. */
void board_init(void);

/* True while received bytes wait in the ring (the main loop sleeps only when none do). */
bool board_serial_pending(void);

/* Cut the drivers' ENABLE line: what the fault handlers do before they halt. */
void board_drivers_off(void);

void board_systick_handler(void);
void board_usart1_handler(void);
void board_exti1_handler(void); /* the hardware e-stop input (PA1) */

#endif
