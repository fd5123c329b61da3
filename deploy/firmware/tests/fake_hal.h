/* The unit tests' hardware layer: a clock the test sets, bytes the test feeds, frames the core sent
 * (decoded), the step rates and driver enable the core commanded, and the e-stop input the test sets. */
#ifndef CLOTHD_FW_FAKE_HAL_H
#define CLOTHD_FW_FAKE_HAL_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "firmware.h"

#define FAKE_MAX_SENT 32

typedef struct {
    uint8_t type;
    uint16_t seq;
    uint8_t payload[256];
    size_t payload_len;
} fake_frame;

extern uint32_t fake_now_ms;
extern int32_t fake_drive_rate[FW_MAX_MODULES];
extern int32_t fake_steer_rate[FW_MAX_MODULES];
extern bool fake_drivers_enabled;
extern bool fake_estop_input; /* what hal_estop_input() returns: the hardware chain open */

/* Forget everything sent and received; the clock back to 1000 ms. */
void fake_hal_reset(void);

/* Bytes hal_serial_read() will hand out next. */
void fake_hal_queue_rx(const uint8_t *data, size_t len);

/* Frames the core has written since the last fake_hal_take_sent(), and forget them. */
size_t fake_hal_take_sent(fake_frame *out, size_t max);

/* Raw bytes written (for the wire-level checks). */
size_t fake_hal_sent_bytes(void);

#endif
