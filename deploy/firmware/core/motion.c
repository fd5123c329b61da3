#include "motion.h"

static float abs_f(float x)
{
    return x < 0.0f ? -x : x;
}

static float clamp_f(float x, float lo, float hi)
{
    if (x < lo) {
        return lo;
    }
    return x > hi ? hi : x;
}

float motion_wrap_rad(float angle_rad)
{
    /* Inputs are bounded (a wire heading of at most 3.28 rad plus pi), so this loops at most twice. */
    while (angle_rad > MOTION_PI) {
        angle_rad -= 2.0f * MOTION_PI;
    }
    while (angle_rad <= -MOTION_PI) {
        angle_rad += 2.0f * MOTION_PI;
    }
    return angle_rad;
}

void motion_init(module_motion *m)
{
    m->target_speed_m_s = 0.0f;
    m->target_heading_rad = 0.0f;
    m->belt_speed_m_s = 0.0f;
    m->heading_rad = 0.0f;
    m->steer_rate_rad_s = 0.0f;
}

void motion_set_target(module_motion *m, const motion_limits *limits, float speed_m_s, float heading_rad)
{
    /* A negative speed is the same motion with the belt turned half round. */
    if (speed_m_s < 0.0f) {
        speed_m_s = -speed_m_s;
        heading_rad += MOTION_PI;
    }
    m->target_speed_m_s = clamp_f(speed_m_s, 0.0f, limits->max_speed_m_s);
    m->target_heading_rad = motion_wrap_rad(heading_rad);
}

void motion_stop(module_motion *m)
{
    m->target_speed_m_s = 0.0f;
}

void motion_cut(module_motion *m)
{
    m->target_speed_m_s = 0.0f;
    m->belt_speed_m_s = 0.0f;
    m->steer_rate_rad_s = 0.0f;
}

void motion_step(module_motion *m, const motion_limits *limits, float dt_s)
{
    float turn_forward_rad = motion_wrap_rad(m->target_heading_rad - m->heading_rad);
    float turn_reverse_rad = motion_wrap_rad(m->target_heading_rad + MOTION_PI - m->heading_rad);
    int reverse = abs_f(turn_reverse_rad) < abs_f(turn_forward_rad);
    float turn_rad = reverse ? turn_reverse_rad : turn_forward_rad;
    float target_belt_m_s = reverse ? -m->target_speed_m_s : m->target_speed_m_s;
    if (m->target_speed_m_s == 0.0f) {
        turn_rad = 0.0f; /* a stopped module has nowhere to point: no steering for nothing */
    }

    float max_turn_rad = limits->steer_rate_limit_rad_s * dt_s;
    turn_rad = clamp_f(turn_rad, -max_turn_rad, max_turn_rad);
    m->heading_rad = motion_wrap_rad(m->heading_rad + turn_rad);
    m->steer_rate_rad_s = dt_s > 0.0f ? turn_rad / dt_s : 0.0f;

    float max_dv_m_s = limits->accel_limit_m_s2 * dt_s;
    m->belt_speed_m_s += clamp_f(target_belt_m_s - m->belt_speed_m_s, -max_dv_m_s, max_dv_m_s);
}
