/*
 * The stepper controller's firmware core (docs/serial-protocol.md, protocol v1): frames in, replies out,
 * the watchdog, the e-stop latch, and every module's motion under its limits. Portable C11: no
 * allocation, no OS calls; the board is reached only through hal.h.
 *
 * Use: fill a fw_config, fw_init() once, then call fw_poll() as often as the board can (at least every
 * few milliseconds: the ramps advance in fw_poll, and the step rates change only there).
 */
#ifndef CLOTHD_FW_FIRMWARE_H
#define CLOTHD_FW_FIRMWARE_H

#include <stdbool.h>
#include <stdint.h>

#include "frame.h"
#include "motion.h"

#ifndef FW_NAME
#define FW_NAME "clothd-fw 1.0"
#endif

/* A COMMAND for n modules decodes to 7 + 4n bytes, and must fit the 1024-byte frame with COBS's
 * overhead: 250 modules is 1007 bytes decoded, 1012 on the wire. */
#ifndef FW_MAX_MODULES
#define FW_MAX_MODULES 250
#endif

/* A stalled loop must not turn into one huge ramp step: dt is capped at this. */
#define FW_MAX_MOTION_STEP_MS 20u

typedef struct {
    uint16_t n_modules; /* 1..FW_MAX_MODULES */
    motion_limits limits;
    float drive_steps_per_m;   /* belt surface travel per drive step, inverted */
    float steer_steps_per_rad; /* turntable rotation per steering step, inverted */
} fw_config;

typedef struct {
    uint32_t frames_ok;
    uint32_t frames_invalid;
    uint32_t commands_applied;
    uint32_t commands_repeated; /* retransmits of the applied seq: acknowledged, not applied again */
    uint32_t nacks_sent;
    uint32_t faults_sent;
    uint32_t watchdog_trips;
    uint32_t estop_input_trips; /* the hardware e-stop input turning active */
} fw_counters;

typedef struct {
    module_motion motion;
    int32_t drive_steps_per_s; /* last rate given to the HAL */
    int32_t steer_steps_per_s;
} fw_module;

typedef struct {
    fw_config config;
    frame_rx rx;
    fw_module modules[FW_MAX_MODULES];
    bool estop_latched;      /* by ESTOP or the hardware input, until ESTOP_CLEAR */
    bool estop_input_active; /* hal_estop_input() at the last look */
    bool watchdog_armed;   /* by the first applied COMMAND */
    bool watchdog_tripped; /* until the next applied COMMAND */
    bool has_applied_seq;
    uint16_t applied_seq;
    uint16_t fault_seq; /* the controller's own counter, for frames it sends unasked */
    uint32_t last_valid_frame_ms;
    uint32_t last_motion_ms;
    fw_counters counters;
} fw_state;

/* The limits hwsim's table uses (max 0.2 m/s, 2 m/s^2, 3 rad/s) and example stepper gearing. */
fw_config fw_default_config(uint16_t n_modules);

/* False (and nothing set up) when the configuration is out of range. */
bool fw_init(fw_state *fw, const fw_config *config, uint32_t now_ms);

/* Read what has arrived, answer it, run the watchdog and advance the ramps: the whole main loop. */
void fw_poll(fw_state *fw);

/* The same, split for tests and for ports that receive in their own way. */
void fw_receive(fw_state *fw, const uint8_t *data, size_t len, uint32_t now_ms);
void fw_tick(fw_state *fw, uint32_t now_ms);

/* Send a FAULT to the host (module FAULT_MODULE_BOARD for the whole board). */
void fw_report_fault(fw_state *fw, uint8_t code, uint16_t module, const char *text);

/* The status flags an ACK carries now. */
uint8_t fw_flags(const fw_state *fw);

#endif
