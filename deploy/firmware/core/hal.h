/*
 * The hardware layer: everything the portable core needs from a board, and nothing more.
 *
 * A port (a microcontroller, or the host build on a pseudo-terminal) provides these functions at link
 * time. The core never allocates, never blocks and never calls the OS; it calls these from fw_poll()
 * only, never from an interrupt, so a port may buffer in its interrupts and drain in these calls.
 */
#ifndef CLOTHD_FW_HAL_H
#define CLOTHD_FW_HAL_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

/* Milliseconds since any fixed start, wrapping at 2^32 (49.7 days): the core only subtracts two readings,
 * so the wrap is harmless. Must be monotonic (not wall-clock time). */
uint32_t hal_now_ms(void);

/* Copy up to max_len received bytes into buf without waiting; returns how many (0: none waiting). */
size_t hal_serial_read(uint8_t *buf, size_t max_len);

/* Send len bytes to the host without waiting long. A port whose line is down or whose buffer is full may
 * drop them: the host retransmits, and the watchdog covers a host that hears nothing. */
void hal_serial_write(const uint8_t *data, size_t len);

/* The drive (belt) stepper of one module: signed step rate, the sign is the direction output; 0 holds
 * still. Called only when the rate changes. */
void hal_drive_set_rate(uint16_t module, int32_t steps_per_s);

/* The steering stepper of one module: signed step rate as above (positive turns counter-clockwise). */
void hal_steer_set_rate(uint16_t module, int32_t steps_per_s);

/* Enable or disable every stepper driver at once. The e-stop disables them: the motors stop without a
 * ramp, whatever step rates are still set. */
void hal_drivers_enable(bool enabled);

/* The cell's hardware e-stop chain (docs/hardware.md, section 3): true while the chain is open (the safety
 * relay has cut the drivers' power), and also once after it opened and closed again between two calls (a
 * port that catches the edge in an interrupt must not lose a pulse shorter than a poll). The core latches
 * its e-stop when this turns true, as for an ESTOP frame, and reports FAULT(ESTOP_INPUT). */
bool hal_estop_input(void);

#endif
