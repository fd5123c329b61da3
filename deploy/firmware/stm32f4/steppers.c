/*
 * Step and direction pulses on the STM32F405: hal_drive_set_rate and hal_steer_set_rate, and the step
 * tick (SysTick's interrupt at STEP_TICK_HZ, 40 kHz), which turns the rates the core sets into STEP
 * pulses and DIR levels on GPIOs.
 *
 * Each stepper ("channel": module m's drive is 2m, its steering 2m + 1) has a phase accumulator driven
 * by elapsed time, not by counting ticks: every tick adds rate x (microseconds since the last tick, read
 * from TIM2) to the phase, and each whole step in it becomes a step owed. A tick then either ends the
 * pulse it started the tick before (STEP low), or, if a step is owed, sets DIR for it, and raises STEP
 * from the next tick on (so DIR leads STEP by a whole tick, 25 us, far above any driver's set-up time).
 * One pulse is one tick high and at least one tick low: up to STEP_TICK_HZ / 2 = 20,000 steps/s, above
 * the 16,000 the core's default gearing asks at 0.2 m/s (docs/hardware.md). On silicon the tick runs on
 * time and a step is owed at most every other tick; where ticks come late (QEMU, which merges timer
 * interrupts the emulated CPU is too slow to take), the steps owed are caught up one pulse per two ticks,
 * so the steps issued still follow the commanded rate over time.
 *
 * Pins (docs/hardware.md): STEP on PC0..PC7 and DIR on PB8..PB15, channel c on PC<c> and PB<8 + c>, so
 * one BSRR write per port per tick sets every pin at once. Only the first BOARD_STEP_MODULES modules have
 * pins (4, the reference board's 8 driver sockets); a build for more modules (the 48 of QEMU's test
 * build) records the other modules' rates and steps nothing for them.
 *
 * step_position[] counts the steps issued per channel (signed: DIR high is negative), for the tests,
 * which read it from QEMU's memory, and for a debugger on the bench.
 */
#include <stdbool.h>
#include <stdint.h>

#include "board.h"
#include "firmware.h"
#include "hal.h"
#include "regs.h"

#define STEP_MAX_RATE ((int32_t)(STEP_TICK_HZ / 2u))
#define STEP_CHANNELS (2u * BOARD_STEP_MODULES)
#define STEP_PHASE_ONE 1000000 /* one step in the phase's unit: steps/s x us */
/* A tick later than this (a debugger halt, not a late interrupt) counts as this long: the phase's
 * rate x dt then stays within int32 (20,000 x 100,000 = 2e9). */
#define STEP_MAX_DT_US 100000u
#define STEP_PIN_FIRST 0u /* PC0.. */
#define DIR_PIN_FIRST 8u  /* PB8.. */

#if BOARD_STEP_MODULES > BOARD_MODULES || STEP_CHANNELS > 8u
#error "BOARD_STEP_MODULES: at most BOARD_MODULES, and 4 (8 STEP pins on PC0..PC7, 8 DIR on PB8..PB15)"
#endif

/* The rates the core set, for every module; the first BOARD_STEP_MODULES are stepped. Written by the
 * main loop, read by the interrupt: a 32-bit store is atomic on the Cortex-M4. */
static volatile int32_t drive_steps_per_s[FW_MAX_MODULES];
static volatile int32_t steer_steps_per_s[FW_MAX_MODULES];
static volatile bool stepping_enabled;

/* The interrupt's own state. */
static int32_t phase[STEP_CHANNELS]; /* steps/s x us not yet owed, |phase| < STEP_PHASE_ONE after a tick */
static int32_t owed[STEP_CHANNELS];  /* whole steps due and not yet issued, signed */
static uint32_t step_high;           /* bit c: channel c's STEP is high (ends next tick) */
static uint32_t dir_negative;        /* bit c: channel c's DIR is set for negative steps */
static uint32_t last_tick_us;

/* Read back through QEMU by tests/test_firmware_qemu.py (and by a debugger on a board). */
volatile int32_t step_position[STEP_CHANNELS];
volatile uint32_t step_ticks;      /* interrupts taken */
volatile uint32_t step_rate_clips; /* rates asked above STEP_MAX_RATE */

static int32_t clip_rate(int32_t steps_per_s)
{
    if (steps_per_s > STEP_MAX_RATE || steps_per_s < -STEP_MAX_RATE) {
        step_rate_clips = step_rate_clips + 1u;
        return steps_per_s > 0 ? STEP_MAX_RATE : -STEP_MAX_RATE;
    }
    return steps_per_s;
}

void hal_drive_set_rate(uint16_t module, int32_t steps_per_s)
{
    if (module < FW_MAX_MODULES) {
        drive_steps_per_s[module] = clip_rate(steps_per_s);
    }
}

void hal_steer_set_rate(uint16_t module, int32_t steps_per_s)
{
    if (module < FW_MAX_MODULES) {
        steer_steps_per_s[module] = clip_rate(steps_per_s);
    }
}

void steppers_enable(bool enabled)
{
    stepping_enabled = enabled;
}

static void gpio_outputs(uint32_t base, uint32_t first_pin, uint32_t count)
{
    for (uint32_t pin = first_pin; pin < first_pin + count; pin++) {
        GPIO_MODER(base) = (GPIO_MODER(base) & ~(3u << (2u * pin))) | (GPIO_MODE_OUTPUT << (2u * pin));
    }
}

void steppers_init(void)
{
    uint32_t step_mask = ((1u << STEP_CHANNELS) - 1u) << STEP_PIN_FIRST;
    uint32_t dir_mask = ((1u << STEP_CHANNELS) - 1u) << DIR_PIN_FIRST;
    GPIO_BSRR(GPIOC_BASE) = step_mask << 16u; /* STEP low, DIR low, before the pins become outputs */
    GPIO_BSRR(GPIOB_BASE) = dir_mask << 16u;
    gpio_outputs(GPIOC_BASE, STEP_PIN_FIRST, STEP_CHANNELS);
    gpio_outputs(GPIOB_BASE, DIR_PIN_FIRST, STEP_CHANNELS);
    last_tick_us = TIM2_CNT;
}

static int32_t channel_rate(uint32_t c)
{
    uint32_t module = c / 2u;
    return (c & 1u) ? steer_steps_per_s[module] : drive_steps_per_s[module];
}

/* One channel's tick: accumulate, then end a pulse, turn DIR, or start a pulse. */
static void channel_tick(uint32_t c, uint32_t dt_us, uint32_t *step_set, uint32_t *dir_set,
                         uint32_t *dir_reset)
{
    uint32_t bit = 1u << c;
    int32_t p = phase[c] + channel_rate(c) * (int32_t)dt_us;
    while (p >= STEP_PHASE_ONE) {
        p -= STEP_PHASE_ONE;
        owed[c]++;
    }
    while (p <= -STEP_PHASE_ONE) {
        p += STEP_PHASE_ONE;
        owed[c]--;
    }
    phase[c] = p;
    if (step_high & bit) {
        step_high &= ~bit; /* the pulse's falling edge: the STEP reset below */
        return;
    }
    if (owed[c] == 0) {
        return;
    }
    bool negative = owed[c] < 0;
    if (negative != ((dir_negative & bit) != 0u)) {
        dir_negative ^= bit; /* DIR first; the step goes out at the next tick */
        *(negative ? dir_set : dir_reset) |= bit;
        return;
    }
    owed[c] += negative ? 1 : -1;
    step_position[c] += negative ? -1 : 1;
    step_high |= bit;
    *step_set |= bit;
}

static void stop_stepping(void)
{
    for (uint32_t c = 0; c < STEP_CHANNELS; c++) {
        phase[c] = 0;
        owed[c] = 0; /* the drivers are off: steps owed now would be issued later, out of place */
    }
    step_high = 0u;
}

void steppers_tick(void)
{
    step_ticks = step_ticks + 1u;
    uint32_t now_us = TIM2_CNT;
    uint32_t dt_us = now_us - last_tick_us;
    last_tick_us = now_us;
    if (dt_us > STEP_MAX_DT_US) {
        dt_us = STEP_MAX_DT_US;
    }
    uint32_t all = (1u << STEP_CHANNELS) - 1u;
    uint32_t step_set = 0u, dir_set = 0u, dir_reset = 0u;
    if (stepping_enabled) {
        for (uint32_t c = 0; c < STEP_CHANNELS; c++) {
            channel_tick(c, dt_us, &step_set, &dir_set, &dir_reset);
        }
    } else {
        stop_stepping();
    }
    /* Every STEP pin not starting a pulse goes low: one write sets and resets them all. */
    GPIO_BSRR(GPIOC_BASE) = (step_set << STEP_PIN_FIRST) | (((all & ~step_set) << STEP_PIN_FIRST) << 16u);
    GPIO_BSRR(GPIOB_BASE) = (dir_set << DIR_PIN_FIRST) | ((dir_reset << DIR_PIN_FIRST) << 16u);
}
