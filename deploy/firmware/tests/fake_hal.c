#include "fake_hal.h"

#include <string.h>

#include "frame.h"
#include "hal.h"

uint32_t fake_now_ms;
int32_t fake_drive_rate[FW_MAX_MODULES];
int32_t fake_steer_rate[FW_MAX_MODULES];
bool fake_drivers_enabled;
bool fake_estop_input;

static uint8_t rx_bytes[4096];
static size_t rx_len;
static size_t rx_read;
static uint8_t tx_bytes[8192];
static size_t tx_len;
static size_t tx_total;

void fake_hal_reset(void)
{
    fake_now_ms = 1000;
    rx_len = rx_read = 0;
    tx_len = tx_total = 0;
    memset(fake_drive_rate, 0, sizeof fake_drive_rate);
    memset(fake_steer_rate, 0, sizeof fake_steer_rate);
    fake_drivers_enabled = false;
    fake_estop_input = false;
}

void fake_hal_queue_rx(const uint8_t *data, size_t len)
{
    if (rx_read == rx_len) {
        rx_len = rx_read = 0;
    }
    size_t room = sizeof rx_bytes - rx_len;
    len = len < room ? len : room;
    memcpy(rx_bytes + rx_len, data, len);
    rx_len += len;
}

size_t fake_hal_take_sent(fake_frame *out, size_t max)
{
    /* Decode what was written with the core's own receiver: the COBS/CRC round trip is checked apart. */
    static frame_rx rx;
    frame_rx_init(&rx);
    size_t n = 0;
    for (size_t i = 0; i < tx_len; i++) {
        frame_msg msg;
        if (frame_rx_push(&rx, tx_bytes[i], &msg) == FRAME_OK && n < max) {
            out[n].type = msg.type;
            out[n].seq = msg.seq;
            out[n].payload_len = msg.payload_len < sizeof out[n].payload ? msg.payload_len
                                                                          : sizeof out[n].payload;
            memcpy(out[n].payload, msg.payload, out[n].payload_len);
            n++;
        }
    }
    tx_len = 0;
    return n;
}

size_t fake_hal_sent_bytes(void)
{
    return tx_total;
}

uint32_t hal_now_ms(void)
{
    return fake_now_ms;
}

size_t hal_serial_read(uint8_t *buf, size_t max_len)
{
    size_t n = rx_len - rx_read;
    n = n < max_len ? n : max_len;
    memcpy(buf, rx_bytes + rx_read, n);
    rx_read += n;
    return n;
}

void hal_serial_write(const uint8_t *data, size_t len)
{
    size_t room = sizeof tx_bytes - tx_len;
    len = len < room ? len : room;
    memcpy(tx_bytes + tx_len, data, len);
    tx_len += len;
    tx_total += len;
}

void hal_drive_set_rate(uint16_t module, int32_t steps_per_s)
{
    fake_drive_rate[module] = steps_per_s;
}

void hal_steer_set_rate(uint16_t module, int32_t steps_per_s)
{
    fake_steer_rate[module] = steps_per_s;
}

void hal_drivers_enable(bool enabled)
{
    fake_drivers_enabled = enabled;
}

bool hal_estop_input(void)
{
    return fake_estop_input;
}
