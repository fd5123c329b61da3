/* The host build's hardware layer: the serial line is a pty's master end, the clock CLOCK_MONOTONIC,
 * and the steppers are arrays that record the commanded step rates (nothing steps). */
#ifndef CLOTHD_FW_HAL_HOST_H
#define CLOTHD_FW_HAL_HOST_H

#include <stdbool.h>
#include <stdint.h>

#include "firmware.h"

void hal_host_init(int serial_fd);

/* What the core last commanded (for the exit summary). */
int32_t hal_host_drive_rate(uint16_t module);
int32_t hal_host_steer_rate(uint16_t module);
bool hal_host_drivers_enabled(void);

#endif
