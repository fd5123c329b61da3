#define _POSIX_C_SOURCE 200809L

#include "hal_host.h"

#include <errno.h>
#include <signal.h>
#include <time.h>
#include <unistd.h>

#include "hal.h"

static int serial_fd = -1;
static int32_t drive_steps_per_s[FW_MAX_MODULES];
static int32_t steer_steps_per_s[FW_MAX_MODULES];
static bool drivers_enabled;
/* The hardware e-stop input, set from a signal handler: the chain open now, and how many times it has
 * opened (so a SIGUSR1 followed at once by a SIGUSR2 is not lost between two polls). Only the handler
 * writes them; hal_estop_input() compares the count with the one it saw last, so a handler that runs in
 * the middle of it loses no opening (a read-then-clear flag would). */
static volatile sig_atomic_t estop_input_open;
static volatile sig_atomic_t estop_input_openings;
static sig_atomic_t estop_input_openings_seen;

void hal_host_init(int fd)
{
    serial_fd = fd;
}

uint32_t hal_now_ms(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    /* Truncated to 32 bits on purpose: the core only subtracts, so the wrap is harmless. */
    return (uint32_t)((uint64_t)ts.tv_sec * 1000u + (uint64_t)ts.tv_nsec / 1000000u);
}

size_t hal_serial_read(uint8_t *buf, size_t max_len)
{
    ssize_t n = read(serial_fd, buf, max_len);
    /* EAGAIN: nothing waiting; EIO: no one has the slave open (we hold it, so only transiently). */
    return n > 0 ? (size_t)n : 0;
}

void hal_serial_write(const uint8_t *data, size_t len)
{
    while (len > 0) {
        ssize_t n = write(serial_fd, data, len);
        if (n < 0 && errno == EINTR) {
            continue;
        }
        if (n <= 0) {
            return; /* the pty's buffer is full (nobody reads): dropped, as on a real line */
        }
        data += n;
        len -= (size_t)n;
    }
}

void hal_drive_set_rate(uint16_t module, int32_t steps_per_s)
{
    if (module < FW_MAX_MODULES) {
        drive_steps_per_s[module] = steps_per_s;
    }
}

void hal_steer_set_rate(uint16_t module, int32_t steps_per_s)
{
    if (module < FW_MAX_MODULES) {
        steer_steps_per_s[module] = steps_per_s;
    }
}

void hal_drivers_enable(bool enabled)
{
    drivers_enabled = enabled;
}

bool hal_estop_input(void)
{
    sig_atomic_t openings = estop_input_openings;
    bool opened = openings != estop_input_openings_seen;
    estop_input_openings_seen = openings;
    return opened || estop_input_open != 0;
}

void hal_host_set_estop_input(bool open)
{
    estop_input_open = open ? 1 : 0;
    if (open) {
        /* the handlers block each other (main.c): one writer at a time; wraps, never overflows */
        estop_input_openings = (estop_input_openings + 1) & 0x7FFF;
    }
}

int32_t hal_host_drive_rate(uint16_t module)
{
    return module < FW_MAX_MODULES ? drive_steps_per_s[module] : 0;
}

int32_t hal_host_steer_rate(uint16_t module)
{
    return module < FW_MAX_MODULES ? steer_steps_per_s[module] : 0;
}

bool hal_host_drivers_enabled(void)
{
    return drivers_enabled;
}
