/*
 * One module's motion: a belt (drive stepper) on a turntable (steering stepper). The host sets a target
 * speed and heading; the module gets there under its limits, whatever the host asked:
 *   - the belt's speed is clipped to max_speed_m_s and changes at most accel_limit_m_s2;
 *   - the heading turns at most steer_rate_limit_rad_s.
 * A belt runs both ways, so (speed, heading) and (-speed, heading + pi) are the same motion: the module
 * takes whichever needs less steering from where it points now.
 */
#ifndef CLOTHD_FW_MOTION_H
#define CLOTHD_FW_MOTION_H

#include <stdint.h>

typedef struct {
    float max_speed_m_s;
    float accel_limit_m_s2;
    float steer_rate_limit_rad_s;
} motion_limits;

typedef struct {
    float target_speed_m_s;    /* >= 0, already clipped to the maximum */
    float target_heading_rad;  /* (-pi, pi] */
    float belt_speed_m_s;      /* signed: negative runs the belt backwards */
    float heading_rad;         /* (-pi, pi] */
    float steer_rate_rad_s;    /* how fast the heading turned in the last step */
} module_motion;

#define MOTION_PI 3.14159265358979f

float motion_wrap_rad(float angle_rad);

void motion_init(module_motion *m);

/* A commanded (signed) speed and heading, clipped to the limits. */
void motion_set_target(module_motion *m, const motion_limits *limits, float speed_m_s, float heading_rad);

/* A controlled stop: target speed zero, reached at the acceleration limit. */
void motion_stop(module_motion *m);

/* Stop at once, without a ramp (the e-stop: the drivers are disabled). */
void motion_cut(module_motion *m);

/* Advance by dt_s towards the target under the limits. */
void motion_step(module_motion *m, const motion_limits *limits, float dt_s);

#endif
