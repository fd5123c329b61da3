/* The message handling: handshake, ACK flags, NACK reasons, seq handling, e-stop latch, watchdog. */
#include <string.h>

#include "check.h"
#include "fake_hal.h"
#include "firmware.h"
#include "protocol.h"

#define N_MODULES 4

static fw_state fw;

static void start(void)
{
    fw_config config = fw_default_config(N_MODULES);
    CHECK(fw_init(&fw, &config, fake_now_ms));
}

static void host_sends(uint8_t type, uint16_t seq, const uint8_t *payload, size_t len)
{
    uint8_t wire[1100];
    size_t wire_len = frame_encode(type, seq, payload, len, wire, sizeof wire);
    CHECK(wire_len > 0);
    fake_hal_queue_rx(wire, wire_len);
    fw_poll(&fw);
}

/* The one frame the firmware answered with (a failed check if it sent none or several). */
static fake_frame reply(void)
{
    fake_frame frames[FAKE_MAX_SENT];
    size_t n = fake_hal_take_sent(frames, FAKE_MAX_SENT);
    CHECK(n == 1);
    if (n == 0) {
        memset(&frames[0], 0, sizeof frames[0]);
    }
    return frames[0];
}

static size_t command_payload(uint8_t *out, uint16_t n, float speed_m_s, float heading_rad)
{
    int16_t speed = (int16_t)(speed_m_s / SPEED_UNIT_M_S + (speed_m_s < 0 ? -0.5f : 0.5f));
    int16_t heading = (int16_t)(heading_rad / HEADING_UNIT_RAD + (heading_rad < 0 ? -0.5f : 0.5f));
    size_t len = 0;
    out[len++] = (uint8_t)(n & 0xFF);
    out[len++] = (uint8_t)(n >> 8);
    for (uint16_t i = 0; i < n; i++) {
        out[len++] = (uint8_t)((uint16_t)speed & 0xFF);
        out[len++] = (uint8_t)((uint16_t)speed >> 8);
        out[len++] = (uint8_t)((uint16_t)heading & 0xFF);
        out[len++] = (uint8_t)((uint16_t)heading >> 8);
    }
    return len;
}

/* Every module to (speed, heading); returns the firmware's answer. */
static fake_frame command(uint16_t seq, float speed_m_s, float heading_rad)
{
    uint8_t payload[2 + 4 * N_MODULES];
    size_t len = command_payload(payload, N_MODULES, speed_m_s, heading_rad);
    host_sends(MSG_COMMAND, seq, payload, len);
    return reply();
}

static void advance_ms(uint32_t ms)
{
    for (uint32_t i = 0; i < ms; i++) {
        fake_now_ms++;
        fw_poll(&fw);
    }
}

static int is_ack(fake_frame f, uint16_t seq, uint8_t flags)
{
    return f.type == MSG_ACK && f.seq == seq && f.payload_len == 1 && f.payload[0] == flags;
}

static int is_nack(fake_frame f, uint16_t seq, uint8_t reason)
{
    return f.type == MSG_NACK && f.seq == seq && f.payload_len == 1 && f.payload[0] == reason;
}

static void hello_is_answered_with_version_modules_and_name(void)
{
    start();
    const uint8_t v1 = PROTOCOL_VERSION;
    host_sends(MSG_HELLO, 300, &v1, 1);
    fake_frame f = reply();
    CHECK(f.type == MSG_HELLO_ACK && f.seq == 300);
    CHECK(f.payload_len == 3 + strlen(FW_NAME));
    CHECK(f.payload[0] == PROTOCOL_VERSION && (f.payload[1] | f.payload[2] << 8) == N_MODULES);
    CHECK(memcmp(f.payload + 3, FW_NAME, strlen(FW_NAME)) == 0);
}

static void hello_with_another_version_is_refused(void)
{
    start();
    const uint8_t v2 = 2;
    host_sends(MSG_HELLO, 1, &v2, 1);
    CHECK(is_nack(reply(), 1, NACK_BAD_VERSION));
    host_sends(MSG_HELLO, 2, NULL, 0);
    CHECK(is_nack(reply(), 2, NACK_BAD_VERSION));
}

static void commands_of_the_wrong_length_and_unknown_types_are_refused(void)
{
    start();
    uint8_t payload[2 + 4 * (N_MODULES + 1)];
    size_t len = command_payload(payload, N_MODULES + 1, 0.1f, 0.0f);
    host_sends(MSG_COMMAND, 10, payload, len); /* n and length agree, but not with the board */
    CHECK(is_nack(reply(), 10, NACK_BAD_LENGTH));
    len = command_payload(payload, N_MODULES, 0.1f, 0.0f);
    host_sends(MSG_COMMAND, 11, payload, len - 1); /* n right, a byte missing */
    CHECK(is_nack(reply(), 11, NACK_BAD_LENGTH));
    host_sends(0x42, 12, NULL, 0);
    CHECK(is_nack(reply(), 12, NACK_UNKNOWN_TYPE));
    host_sends(MSG_ACK, 13, NULL, 0); /* a controller's message sent to the controller */
    CHECK(is_nack(reply(), 13, NACK_UNKNOWN_TYPE));
    CHECK(fw.counters.commands_applied == 0 && fw.counters.nacks_sent == 4);
}

static void a_retransmit_of_the_applied_seq_is_only_acknowledged(void)
{
    start();
    CHECK(is_ack(command(20, 0.1f, 0.0f), 20, 0));
    CHECK(is_ack(command(20, 0.15f, 1.0f), 20, 0)); /* same seq: acknowledged, not applied */
    CHECK_NEAR(fw.modules[0].motion.target_speed_m_s, 0.1, 1e-4);
    CHECK(fw.counters.commands_applied == 1 && fw.counters.commands_repeated == 1);
    CHECK(is_ack(command(21, 0.15f, 1.0f), 21, 0));
    CHECK_NEAR(fw.modules[0].motion.target_speed_m_s, 0.15, 1e-4);
    CHECK_NEAR(fw.modules[0].motion.target_heading_rad, 1.0, 1e-4);
    /* A new session (HELLO) may start its count anywhere: its first command is applied. */
    const uint8_t v1 = PROTOCOL_VERSION;
    host_sends(MSG_HELLO, 1, &v1, 1);
    reply();
    CHECK(is_ack(command(21, 0.05f, 0.0f), 21, 0));
    CHECK_NEAR(fw.modules[0].motion.target_speed_m_s, 0.05, 1e-4);
}

static void estop_cuts_at_once_latches_and_refuses_commands_until_cleared(void)
{
    start();
    command(1, 0.2f, 0.0f);
    advance_ms(200); /* well past the ramp: running at full speed */
    CHECK_NEAR(fw.modules[0].motion.belt_speed_m_s, 0.2, 1e-4);
    CHECK(fake_drive_rate[0] != 0 && fake_drivers_enabled);

    host_sends(MSG_ESTOP, 2, NULL, 0);
    CHECK(is_ack(reply(), 2, FLAG_ESTOP));
    CHECK(!fake_drivers_enabled); /* no ramp: the drivers are off at once */
    for (uint16_t i = 0; i < N_MODULES; i++) {
        CHECK(fw.modules[i].motion.belt_speed_m_s == 0.0f && fake_drive_rate[i] == 0);
    }
    CHECK(is_nack(command(3, 0.1f, 0.0f), 3, NACK_ESTOPPED));
    host_sends(MSG_PING, 4, NULL, 0);
    CHECK(is_ack(reply(), 4, FLAG_ESTOP));
    advance_ms(100);
    CHECK(fw.modules[0].motion.belt_speed_m_s == 0.0f); /* the refused command moved nothing */

    host_sends(MSG_ESTOP_CLEAR, 5, NULL, 0);
    CHECK(is_ack(reply(), 5, 0));
    CHECK(fake_drivers_enabled);
    advance_ms(50);
    CHECK(fw.modules[0].motion.belt_speed_m_s == 0.0f); /* cleared, but still stopped until told */
    CHECK(is_ack(command(6, 0.1f, 0.0f), 6, 0));
    advance_ms(100);
    CHECK_NEAR(fw.modules[0].motion.belt_speed_m_s, 0.1, 1e-4);
}

static void a_host_that_only_said_hello_is_no_watchdog_fault(void)
{
    start();
    const uint8_t v1 = PROTOCOL_VERSION;
    host_sends(MSG_HELLO, 1, &v1, 1);
    reply();
    advance_ms(2000);
    fake_frame frames[FAKE_MAX_SENT];
    CHECK(fake_hal_take_sent(frames, FAKE_MAX_SENT) == 0);
    CHECK(!fw.watchdog_tripped);
}

static void the_watchdog_stops_the_modules_250_ms_after_the_last_frame(void)
{
    start();
    command(1, 0.2f, 0.0f);
    advance_ms(200);
    host_sends(MSG_PING, 2, NULL, 0); /* any valid frame feeds it */
    reply();
    advance_ms(WATCHDOG_TIMEOUT_MS);
    fake_frame frames[FAKE_MAX_SENT];
    CHECK(fake_hal_take_sent(frames, FAKE_MAX_SENT) == 0 && !fw.watchdog_tripped);
    CHECK_NEAR(fw.modules[0].motion.belt_speed_m_s, 0.2, 1e-4);

    advance_ms(1);
    fake_frame fault = reply();
    CHECK(fault.type == MSG_FAULT && fault.payload_len > 3 && fault.payload[0] == FAULT_WATCHDOG);
    CHECK((fault.payload[1] | fault.payload[2] << 8) == FAULT_MODULE_BOARD);
    CHECK(fw.watchdog_tripped && fw.modules[0].motion.target_speed_m_s == 0.0f);
    /* A controlled stop at the acceleration limit (2 m/s^2): 0.2 m/s takes 100 ms, not one step. */
    CHECK(fw.modules[0].motion.belt_speed_m_s > 0.19f);
    advance_ms(50);
    CHECK_NEAR(fw.modules[0].motion.belt_speed_m_s, 0.098, 1e-4); /* 1 + 50 ms of ramp */
    advance_ms(60);
    CHECK(fw.modules[0].motion.belt_speed_m_s == 0.0f && fake_drive_rate[0] == 0);
    CHECK(fake_hal_take_sent(frames, FAKE_MAX_SENT) == 0); /* reported once, not every tick */

    host_sends(MSG_PING, 3, NULL, 0);
    CHECK(is_ack(reply(), 3, FLAG_WATCHDOG)); /* the flag stays until the next command */
    CHECK(is_ack(command(4, 0.1f, 0.0f), 4, 0));
}

static void noise_does_not_feed_the_watchdog(void)
{
    start();
    command(1, 0.1f, 0.0f);
    const uint8_t noise[] = {0x12, 0x34, 0x00, 0x56, 0x00};
    for (int i = 0; i < 30; i++) {
        advance_ms(10);
        fake_hal_queue_rx(noise, sizeof noise);
    }
    CHECK(fw.watchdog_tripped && fw.counters.frames_invalid > 0);
}

static int is_estop_input_fault(fake_frame f)
{
    return f.type == MSG_FAULT && f.payload_len > 3 && f.payload[0] == FAULT_ESTOP_INPUT &&
           (f.payload[1] | f.payload[2] << 8) == FAULT_MODULE_BOARD;
}

static void the_estop_input_latches_like_estop_and_reports_a_fault_once(void)
{
    start();
    command(1, 0.2f, 0.0f);
    advance_ms(200);
    CHECK(fake_drive_rate[0] != 0 && fake_drivers_enabled);

    fake_estop_input = true; /* the safety relay opens the chain */
    advance_ms(1);
    CHECK(is_estop_input_fault(reply()));
    CHECK(fw.estop_latched && !fake_drivers_enabled && fw.counters.estop_input_trips == 1);
    for (uint16_t i = 0; i < N_MODULES; i++) {
        CHECK(fw.modules[i].motion.belt_speed_m_s == 0.0f && fake_drive_rate[i] == 0); /* no ramp */
    }
    CHECK(is_nack(command(2, 0.1f, 0.0f), 2, NACK_ESTOPPED));
    host_sends(MSG_PING, 3, NULL, 0);
    CHECK(is_ack(reply(), 3, FLAG_ESTOP));
    advance_ms(100);
    fake_frame frames[FAKE_MAX_SENT];
    CHECK(fake_hal_take_sent(frames, FAKE_MAX_SENT) == 0); /* reported once, not every tick */

    /* A clear while the chain is still open is refused: the ACK keeps the flag, the drivers stay off. */
    host_sends(MSG_ESTOP_CLEAR, 4, NULL, 0);
    CHECK(is_ack(reply(), 4, FLAG_ESTOP));
    CHECK(fw.estop_latched && !fake_drivers_enabled);

    /* The chain closing (the button released, the relay reset) restarts nothing: still latched. */
    fake_estop_input = false;
    advance_ms(50);
    host_sends(MSG_PING, 5, NULL, 0);
    CHECK(is_ack(reply(), 5, FLAG_ESTOP));
    CHECK(!fake_drivers_enabled);

    host_sends(MSG_ESTOP_CLEAR, 6, NULL, 0);
    CHECK(is_ack(reply(), 6, 0));
    CHECK(fake_drivers_enabled);
    advance_ms(50);
    CHECK(fw.modules[0].motion.belt_speed_m_s == 0.0f); /* stopped until the next command */
    CHECK(is_ack(command(7, 0.1f, 0.0f), 7, 0));
    advance_ms(100);
    CHECK_NEAR(fw.modules[0].motion.belt_speed_m_s, 0.1, 1e-4);
}

static void an_estop_input_open_at_power_up_latches_at_the_first_tick(void)
{
    fake_estop_input = true;
    start();
    CHECK(fake_drivers_enabled); /* fw_init enables; the first tick looks at the input */
    advance_ms(1);
    CHECK(is_estop_input_fault(reply()));
    CHECK(fw.estop_latched && !fake_drivers_enabled);
    CHECK(is_nack(command(1, 0.1f, 0.0f), 1, NACK_ESTOPPED));
}

static void a_pulse_on_the_estop_input_latches_too(void)
{
    start();
    command(1, 0.1f, 0.0f);
    advance_ms(50);
    fake_estop_input = true; /* a port reports a pulse shorter than a poll once */
    advance_ms(1);
    fake_estop_input = false;
    advance_ms(1);
    CHECK(is_estop_input_fault(reply()));
    CHECK(fw.estop_latched && !fake_drivers_enabled);
    host_sends(MSG_ESTOP_CLEAR, 2, NULL, 0);
    CHECK(is_ack(reply(), 2, 0)); /* the chain is closed again: the clear is taken */
    fake_estop_input = true;      /* and a second opening trips again */
    advance_ms(1);
    CHECK(is_estop_input_fault(reply()));
    CHECK(fw.estop_latched && fw.counters.estop_input_trips == 2);
}

void run_protocol_tests(void)
{
    RUN_TEST(hello_is_answered_with_version_modules_and_name);
    RUN_TEST(hello_with_another_version_is_refused);
    RUN_TEST(commands_of_the_wrong_length_and_unknown_types_are_refused);
    RUN_TEST(a_retransmit_of_the_applied_seq_is_only_acknowledged);
    RUN_TEST(estop_cuts_at_once_latches_and_refuses_commands_until_cleared);
    RUN_TEST(a_host_that_only_said_hello_is_no_watchdog_fault);
    RUN_TEST(the_watchdog_stops_the_modules_250_ms_after_the_last_frame);
    RUN_TEST(noise_does_not_feed_the_watchdog);
    RUN_TEST(the_estop_input_latches_like_estop_and_reports_a_fault_once);
    RUN_TEST(an_estop_input_open_at_power_up_latches_at_the_first_tick);
    RUN_TEST(a_pulse_on_the_estop_input_latches_too);
}
