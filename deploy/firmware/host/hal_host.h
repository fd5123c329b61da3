/* The host build's hardware layer: the serial line is a pty's master end, the clock CLOCK_MONOTONIC,
 * the steppers are arrays that record the commanded step rates (nothing steps), and the hardware e-stop
 * input is whatever main.c's signal handlers last set (SIGUSR1 opens the chain, SIGUSR2 closes it). */
#ifndef CLOTHD_FW_HAL_HOST_H
#define CLOTHD_FW_HAL_HOST_H

#include <stdbool.h>
#include <stdint.h>

#include "firmware.h"

void hal_host_init(int serial_fd);

/* The hardware e-stop chain open (true) or closed; async-signal-safe (it only sets two flags), and
 * called from one handler at a time (main.c blocks SIGUSR1 and SIGUSR2 in either). */
void hal_host_set_estop_input(bool open);

/* What the core last commanded (for the exit summary). */
int32_t hal_host_drive_rate(uint16_t module);
int32_t hal_host_steer_rate(uint16_t module);
bool hal_host_drivers_enabled(void);

#endif
