/* The ramps: the acceleration limit, the steering-rate limit and the speed limit hold whatever the host
 * asks; a negative speed or a heading behind the module is reached by reversing the belt. */
#include "check.h"
#include "fake_hal.h"
#include "motion.h"

static const motion_limits limits = {
    .max_speed_m_s = 0.2f,
    .accel_limit_m_s2 = 2.0f,
    .steer_rate_limit_rad_s = 3.0f,
};

#define DT_S 0.001f

static void run_ms(module_motion *m, int ms)
{
    for (int i = 0; i < ms; i++) {
        motion_step(m, &limits, DT_S);
    }
}

static void speed_ramps_at_the_acceleration_limit(void)
{
    module_motion m;
    motion_init(&m);
    motion_set_target(&m, &limits, 0.2f, 0.0f);
    float previous_m_s = 0.0f;
    for (int i = 0; i < 150; i++) {
        run_ms(&m, 1);
        float dv_m_s = m.belt_speed_m_s - previous_m_s;
        CHECK(dv_m_s <= limits.accel_limit_m_s2 * DT_S + 1e-6f);
        previous_m_s = m.belt_speed_m_s;
    }
    CHECK_NEAR(m.belt_speed_m_s, 0.2, 1e-5); /* 100 ms at 2 m/s^2 */
    motion_stop(&m);
    run_ms(&m, 50);
    CHECK_NEAR(m.belt_speed_m_s, 0.1, 1e-4); /* a controlled stop, at the same limit */
}

static void speed_is_clipped_to_the_maximum(void)
{
    module_motion m;
    motion_init(&m);
    motion_set_target(&m, &limits, 3.2767f, 0.0f); /* the most the wire can say */
    CHECK_NEAR(m.target_speed_m_s, 0.2, 1e-6);
    run_ms(&m, 1000);
    CHECK(m.belt_speed_m_s <= 0.2f + 1e-6f);
}

static void heading_turns_at_the_steering_rate_limit(void)
{
    module_motion m;
    motion_init(&m);
    motion_set_target(&m, &limits, 0.1f, 1.5f);
    run_ms(&m, 100);
    CHECK_NEAR(m.heading_rad, 0.3, 1e-4); /* 3 rad/s for 100 ms */
    CHECK_NEAR(m.steer_rate_rad_s, 3.0, 1e-3);
    run_ms(&m, 500);
    CHECK_NEAR(m.heading_rad, 1.5, 1e-4);
    CHECK_NEAR(m.steer_rate_rad_s, 0.0, 1e-6); /* there: the steering stops */
}

static void the_shorter_turn_wins_by_reversing_the_belt(void)
{
    module_motion m;
    motion_init(&m);
    motion_set_target(&m, &limits, -0.1f, 0.0f); /* = 0.1 m/s towards pi: reverse instead of turning */
    CHECK_NEAR(m.target_heading_rad, MOTION_PI, 1e-4);
    run_ms(&m, 200);
    CHECK_NEAR(m.heading_rad, 0.0, 1e-6);
    CHECK_NEAR(m.belt_speed_m_s, -0.1, 1e-5);
    motion_set_target(&m, &limits, 0.1f, 3.0f); /* 3 rad ahead, or 0.14 rad behind reversed */
    run_ms(&m, 100);
    CHECK_NEAR(m.heading_rad, 3.0 - MOTION_PI, 1e-4);
    CHECK_NEAR(m.belt_speed_m_s, -0.1, 1e-5);
}

static void a_stopped_target_does_not_steer(void)
{
    module_motion m;
    motion_init(&m);
    motion_set_target(&m, &limits, 0.0f, 2.0f);
    run_ms(&m, 100);
    CHECK(m.heading_rad == 0.0f && m.belt_speed_m_s == 0.0f);
}

static void headings_wrap_into_minus_pi_to_pi(void)
{
    CHECK_NEAR(motion_wrap_rad(MOTION_PI), MOTION_PI, 1e-6);
    CHECK_NEAR(motion_wrap_rad(-MOTION_PI), MOTION_PI, 1e-6);
    CHECK_NEAR(motion_wrap_rad(3.2767f + MOTION_PI), 3.2767f - MOTION_PI, 1e-5);
    CHECK_NEAR(motion_wrap_rad(-3.2767f), 2.0f * MOTION_PI - 3.2767f, 1e-5);
}

static void the_firmware_turns_speeds_into_step_rates(void)
{
    static fw_state fw;
    fw_config config = fw_default_config(2);
    CHECK(fw_init(&fw, &config, fake_now_ms));
    fw.modules[1].motion.belt_speed_m_s = 0.1f;
    fw.modules[1].motion.target_speed_m_s = 0.1f;
    fake_now_ms += 1;
    fw_tick(&fw, fake_now_ms);
    CHECK(fake_drive_rate[0] == 0);
    CHECK(fake_drive_rate[1] == (int32_t)(0.1f * config.drive_steps_per_m + 0.5f));
    fw_config too_many = fw_default_config(FW_MAX_MODULES + 1);
    CHECK(!fw_init(&fw, &too_many, fake_now_ms));
}

void run_motion_tests(void)
{
    RUN_TEST(speed_ramps_at_the_acceleration_limit);
    RUN_TEST(speed_is_clipped_to_the_maximum);
    RUN_TEST(heading_turns_at_the_steering_rate_limit);
    RUN_TEST(the_shorter_turn_wins_by_reversing_the_belt);
    RUN_TEST(a_stopped_target_does_not_steer);
    RUN_TEST(headings_wrap_into_minus_pi_to_pi);
    RUN_TEST(the_firmware_turns_speeds_into_step_rates);
}
