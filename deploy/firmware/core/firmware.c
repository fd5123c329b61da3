#include "firmware.h"

#include "hal.h"
#include "protocol.h"

#define FW_TX_BYTES 320      /* the biggest reply (HELLO_ACK, FAULT) with COBS overhead and delimiter */
#define FW_RX_CHUNK_BYTES 64 /* bytes read from the HAL per call */
#define FW_FAULT_TEXT_MAX 200

fw_config fw_default_config(uint16_t n_modules)
{
    fw_config config;
    config.n_modules = n_modules;
    config.limits.max_speed_m_s = 0.2f;
    config.limits.accel_limit_m_s2 = 2.0f;
    config.limits.steer_rate_limit_rad_s = 3.0f;
    /* Example gearing: 200-step motor, 16 microsteps, 40 mm of belt per revolution; the turntable
     * geared 4:1 from the same motor. A port sets its own. */
    config.drive_steps_per_m = 200.0f * 16.0f / 0.040f;
    config.steer_steps_per_rad = 200.0f * 16.0f * 4.0f / (2.0f * MOTION_PI);
    return config;
}

static bool config_valid(const fw_config *c)
{
    return c->n_modules >= 1 && c->n_modules <= FW_MAX_MODULES && c->limits.max_speed_m_s > 0.0f &&
           c->limits.accel_limit_m_s2 > 0.0f && c->limits.steer_rate_limit_rad_s > 0.0f &&
           c->drive_steps_per_m > 0.0f && c->steer_steps_per_rad > 0.0f;
}

bool fw_init(fw_state *fw, const fw_config *config, uint32_t now_ms)
{
    if (!config_valid(config)) {
        return false;
    }
    fw->config = *config;
    frame_rx_init(&fw->rx);
    for (uint16_t i = 0; i < config->n_modules; i++) {
        motion_init(&fw->modules[i].motion);
        fw->modules[i].drive_steps_per_s = 0;
        fw->modules[i].steer_steps_per_s = 0;
        hal_drive_set_rate(i, 0);
        hal_steer_set_rate(i, 0);
    }
    fw->estop_latched = false;
    fw->estop_input_active = false; /* an input already open at power-up latches at the first tick */
    fw->watchdog_armed = false;
    fw->watchdog_tripped = false;
    fw->has_applied_seq = false;
    fw->applied_seq = 0;
    fw->fault_seq = 0;
    fw->last_valid_frame_ms = now_ms;
    fw->last_motion_ms = now_ms;
    fw->counters = (fw_counters){0};
    hal_drivers_enable(true);
    return true;
}

uint8_t fw_flags(const fw_state *fw)
{
    return (uint8_t)((fw->estop_latched ? FLAG_ESTOP : 0) | (fw->watchdog_tripped ? FLAG_WATCHDOG : 0));
}

/* -- sending ------------------------------------------------------------------------------------- */

static void send_frame(uint8_t type, uint16_t seq, const uint8_t *payload, size_t payload_len)
{
    uint8_t wire[FW_TX_BYTES];
    size_t len = frame_encode(type, seq, payload, payload_len, wire, sizeof wire);
    if (len > 0) {
        hal_serial_write(wire, len);
    }
}

static void send_ack(const fw_state *fw, uint16_t seq)
{
    uint8_t flags = fw_flags(fw);
    send_frame(MSG_ACK, seq, &flags, 1);
}

static void send_nack(fw_state *fw, uint16_t seq, uint8_t reason)
{
    fw->counters.nacks_sent++;
    send_frame(MSG_NACK, seq, &reason, 1);
}

void fw_report_fault(fw_state *fw, uint8_t code, uint16_t module, const char *text)
{
    uint8_t payload[3 + FW_FAULT_TEXT_MAX];
    size_t len = 0;
    payload[len++] = code;
    payload[len++] = (uint8_t)(module & 0xFF);
    payload[len++] = (uint8_t)(module >> 8);
    for (size_t i = 0; text[i] != '\0' && i < FW_FAULT_TEXT_MAX; i++) {
        payload[len++] = (uint8_t)text[i];
    }
    /* Unasked: the reply-seq rule does not apply, so the controller numbers these itself. */
    fw->fault_seq = (uint16_t)(fw->fault_seq + 1);
    fw->counters.faults_sent++;
    send_frame(MSG_FAULT, fw->fault_seq, payload, len);
}

/* -- the drives ---------------------------------------------------------------------------------- */

static int32_t round_to_i32(float x)
{
    return (int32_t)(x < 0.0f ? x - 0.5f : x + 0.5f);
}

/* Tell the HAL each module's step rates, only where they changed (a port may reprogram a timer). */
static void output_step_rates(fw_state *fw)
{
    for (uint16_t i = 0; i < fw->config.n_modules; i++) {
        fw_module *mod = &fw->modules[i];
        int32_t drive = round_to_i32(mod->motion.belt_speed_m_s * fw->config.drive_steps_per_m);
        int32_t steer = round_to_i32(mod->motion.steer_rate_rad_s * fw->config.steer_steps_per_rad);
        if (drive != mod->drive_steps_per_s) {
            mod->drive_steps_per_s = drive;
            hal_drive_set_rate(i, drive);
        }
        if (steer != mod->steer_steps_per_s) {
            mod->steer_steps_per_s = steer;
            hal_steer_set_rate(i, steer);
        }
    }
}

static void stop_all_modules(fw_state *fw)
{
    for (uint16_t i = 0; i < fw->config.n_modules; i++) {
        motion_stop(&fw->modules[i].motion);
    }
}

static void cut_all_modules(fw_state *fw)
{
    hal_drivers_enable(false); /* first: the motors stop now, whatever the rates below */
    for (uint16_t i = 0; i < fw->config.n_modules; i++) {
        motion_cut(&fw->modules[i].motion);
    }
    output_step_rates(fw);
}

/* -- the messages -------------------------------------------------------------------------------- */

static int16_t read_i16_le(const uint8_t *p)
{
    return (int16_t)(uint16_t)(p[0] | (p[1] << 8));
}

static void handle_hello(fw_state *fw, const frame_msg *msg)
{
    if (msg->payload_len < 1 || msg->payload[0] != PROTOCOL_VERSION) {
        send_nack(fw, msg->seq, NACK_BAD_VERSION);
        return;
    }
    /* A HELLO starts a new host session whose seq count starts afresh: its first COMMAND must not be
     * taken for a retransmit of the last session's. */
    fw->has_applied_seq = false;
    uint8_t payload[3 + sizeof FW_NAME];
    size_t len = 0;
    payload[len++] = PROTOCOL_VERSION;
    payload[len++] = (uint8_t)(fw->config.n_modules & 0xFF);
    payload[len++] = (uint8_t)(fw->config.n_modules >> 8);
    for (size_t i = 0; i < sizeof FW_NAME - 1; i++) {
        payload[len++] = (uint8_t)FW_NAME[i];
    }
    send_frame(MSG_HELLO_ACK, msg->seq, payload, len);
}

static bool command_length_ok(const fw_state *fw, const frame_msg *msg)
{
    size_t n = fw->config.n_modules;
    if (msg->payload_len != 2 + 4 * n) {
        return false;
    }
    return (size_t)(msg->payload[0] | (msg->payload[1] << 8)) == n;
}

static void apply_command(fw_state *fw, const frame_msg *msg)
{
    const uint8_t *pair = msg->payload + 2;
    for (uint16_t i = 0; i < fw->config.n_modules; i++, pair += 4) {
        float speed_m_s = (float)read_i16_le(pair) * SPEED_UNIT_M_S;
        float heading_rad = (float)read_i16_le(pair + 2) * HEADING_UNIT_RAD;
        motion_set_target(&fw->modules[i].motion, &fw->config.limits, speed_m_s, heading_rad);
    }
    fw->has_applied_seq = true;
    fw->applied_seq = msg->seq;
    fw->watchdog_armed = true;
    fw->watchdog_tripped = false;
    fw->counters.commands_applied++;
}

static void handle_command(fw_state *fw, const frame_msg *msg)
{
    if (!command_length_ok(fw, msg)) {
        send_nack(fw, msg->seq, NACK_BAD_LENGTH);
        return;
    }
    if (fw->estop_latched) {
        send_nack(fw, msg->seq, NACK_ESTOPPED);
        return;
    }
    if (fw->has_applied_seq && msg->seq == fw->applied_seq) {
        fw->counters.commands_repeated++; /* our ACK was lost: acknowledge again, apply nothing */
    } else {
        apply_command(fw, msg);
    }
    send_ack(fw, msg->seq);
}

static void handle_estop(fw_state *fw, const frame_msg *msg)
{
    cut_all_modules(fw);
    fw->estop_latched = true;
    send_ack(fw, msg->seq);
}

/* The hardware e-stop input: its turning active latches the e-stop exactly as an ESTOP frame does, and
 * the host hears of it unasked (the ACK flags then show the latch). */
static void check_estop_input(fw_state *fw)
{
    bool active = hal_estop_input();
    if (active && !fw->estop_input_active) {
        cut_all_modules(fw);
        fw->estop_latched = true;
        fw->counters.estop_input_trips++;
        fw_report_fault(fw, FAULT_ESTOP_INPUT, FAULT_MODULE_BOARD,
                        "hardware e-stop input: drivers cut, e-stop latched");
    }
    fw->estop_input_active = active;
}

static void handle_estop_clear(fw_state *fw, const frame_msg *msg)
{
    /* The modules stay stopped (targets zero) until the host's next COMMAND. While the hardware chain is
     * still open the latch holds: the ACK carries the e-stop flag, and the host clears again later. */
    check_estop_input(fw);
    if (fw->estop_latched && !fw->estop_input_active) {
        fw->estop_latched = false;
        hal_drivers_enable(true);
    }
    send_ack(fw, msg->seq);
}

static void handle_frame(fw_state *fw, const frame_msg *msg, uint32_t now_ms)
{
    fw->counters.frames_ok++;
    fw->last_valid_frame_ms = now_ms; /* any valid frame feeds the watchdog, a PING included */
    switch (msg->type) {
    case MSG_HELLO:
        handle_hello(fw, msg);
        break;
    case MSG_COMMAND:
        handle_command(fw, msg);
        break;
    case MSG_ESTOP:
        handle_estop(fw, msg);
        break;
    case MSG_ESTOP_CLEAR:
        handle_estop_clear(fw, msg);
        break;
    case MSG_PING:
        send_ack(fw, msg->seq);
        break;
    default:
        send_nack(fw, msg->seq, NACK_UNKNOWN_TYPE);
        break;
    }
}

void fw_receive(fw_state *fw, const uint8_t *data, size_t len, uint32_t now_ms)
{
    for (size_t i = 0; i < len; i++) {
        frame_msg msg;
        frame_result result = frame_rx_push(&fw->rx, data[i], &msg);
        if (result == FRAME_OK) {
            handle_frame(fw, &msg, now_ms);
        } else if (result == FRAME_INVALID) {
            fw->counters.frames_invalid++; /* noise does not feed the watchdog */
        }
    }
}

/* -- the watchdog and the ramps ------------------------------------------------------------------ */

static void check_watchdog(fw_state *fw, uint32_t now_ms)
{
    /* Before the first COMMAND nothing was driven, so a silent host leaves nothing to stop. */
    if (!fw->watchdog_armed || fw->watchdog_tripped) {
        return;
    }
    if ((uint32_t)(now_ms - fw->last_valid_frame_ms) <= WATCHDOG_TIMEOUT_MS) {
        return;
    }
    stop_all_modules(fw); /* a controlled stop, at the acceleration limit */
    fw->watchdog_tripped = true;
    fw->counters.watchdog_trips++;
    fw_report_fault(fw, FAULT_WATCHDOG, FAULT_MODULE_BOARD, "host silent: all modules stopped");
}

static void advance_motion(fw_state *fw, uint32_t now_ms)
{
    uint32_t elapsed_ms = now_ms - fw->last_motion_ms;
    if (elapsed_ms == 0) {
        return;
    }
    fw->last_motion_ms = now_ms;
    if (elapsed_ms > FW_MAX_MOTION_STEP_MS) {
        elapsed_ms = FW_MAX_MOTION_STEP_MS;
    }
    float dt_s = (float)elapsed_ms * 1e-3f;
    for (uint16_t i = 0; i < fw->config.n_modules; i++) {
        motion_step(&fw->modules[i].motion, &fw->config.limits, dt_s);
    }
    output_step_rates(fw);
}

void fw_tick(fw_state *fw, uint32_t now_ms)
{
    check_estop_input(fw);
    check_watchdog(fw, now_ms);
    if (fw->estop_latched) {
        fw->last_motion_ms = now_ms; /* drivers disabled: nothing moves, nothing ramps */
        return;
    }
    advance_motion(fw, now_ms);
}

void fw_poll(fw_state *fw)
{
    uint8_t chunk[FW_RX_CHUNK_BYTES];
    size_t got;
    /* Bounded: a host flooding the line must not starve the watchdog and the ramps. */
    for (int reads = 0; reads < 16 && (got = hal_serial_read(chunk, sizeof chunk)) > 0; reads++) {
        fw_receive(fw, chunk, got, hal_now_ms());
    }
    fw_tick(fw, hal_now_ms());
}
