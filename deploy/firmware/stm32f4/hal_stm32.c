/*
 * hal.h on the STM32F405 (and QEMU's netduinoplus2 model of it):
 *
 * - hal_now_ms: TIM2 counts microseconds, free-running over its 32 bits, and hal_now_ms extends that to
 *   milliseconds. Not a count of SysTick interrupts: QEMU merges timer interrupts the guest is too slow
 *   to take, and on this project's test machines a tick count fell 4 % behind the host's clock when idle
 *   and over 30 % behind under load, which stretched the 250 ms watchdog past 300 ms; TIM2's count is
 *   computed from QEMU's clock itself. (On silicon neither drifts.) SysTick interrupts at STEP_TICK_HZ
 *   (40 kHz): it is the step tick, and it wakes the main loop, so the ramps and the watchdog advance while
 *   no byte arrives.
 * - the serial line: USART1 (PA9 TX, PA10 RX, AF7), the first -serial of QEMU's machine. Received bytes
 *   go into a ring from the RXNE interrupt and fw_poll drains it; sent bytes are written out by polling
 *   TXE (an ACK is 8 bytes on the wire: ~90 us at 921600 baud).
 * - the steppers: steppers.c, STEP/DIR pulses from SysTick's interrupt at 40 kHz. (TIM3 was the first
 *   choice; QEMU 7.2's model of TIM2..TIM5 reschedules its update interrupt wrongly once it has fired,
 *   so a periodic TIMx interrupt cannot be tested there; its SysTick is right.)
 * - the drivers' ENABLE line: PB0, active low (the usual ENN input of a stepper driver).
 * - the hardware e-stop input: PA1, pulled up, high while the chain is open (docs/hardware.md, section 3:
 *   the safety relay's SAFE_EN holds it low through an optocoupler, so a broken wire reads as open too).
 *   EXTI1 catches the rising edge: its interrupt cuts ENABLE at once and counts the edge, and
 *   hal_estop_input reports the edge or the level to the core, which latches. QEMU models no GPIO (the
 *   level reads 0, closed) but does model SYSCFG and EXTI: tests/test_firmware_qemu.py raises the line
 *   through QEMU's qtest interface.
 */
#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "board.h"
#include "firmware.h"
#include "hal.h"
#include "regs.h"

/* The clocks: the core clock SysTick counts, TIM2's input clock, and the APB2 clock USART1 runs from.
 *
 * BOARD_CLOCKS_QEMU (make stm32, the default): QEMU's netduinoplus2 runs the Cortex-M4 at a fixed
 * 168 MHz and its TIM2 model at 1 GHz, whatever RCC says (RCC is not modelled), and ignores the baud
 * rate. BOARD_CLOCKS_HSI (make stm32 STM32_CLOCKS=hsi): a real STM32F405 left on the 16 MHz HSI it starts
 * on, every bus undivided (no PLL set-up needed; 921600 baud comes out 2 % fast, within a UART's margin).
 * A board that sets up the PLL (168 MHz, APB1 timers 84 MHz, APB2 84 MHz) adds that code and its own
 * figures here. */
#if defined(BOARD_CLOCKS_HSI)
#define SYSCLK_HZ 16000000u
#define TIM2_CLOCK_HZ 16000000u
#define APB2_HZ 16000000u
#elif defined(BOARD_CLOCKS_QEMU)
#define SYSCLK_HZ 168000000u
#define TIM2_CLOCK_HZ 1000000000u
#define APB2_HZ 84000000u
#else
#error "define BOARD_CLOCKS_QEMU or BOARD_CLOCKS_HSI (the Makefile's STM32_CLOCKS)"
#endif
#define SERIAL_BAUD 921600u /* clothd's stepper.baud default */
#define MICROSECONDS_PER_MS 1000u

#define DRIVERS_ENABLE_PIN 0u /* PB0 */
#define ESTOP_INPUT_PIN 1u    /* PA1, EXTI line 1 */
#define USART1_TX_PIN 9u      /* PA9 */
#define USART1_RX_PIN 10u     /* PA10 */

/* A power of two, so the free-running 32-bit indices stay consistent across their wrap. Larger than
 * one 1024-byte frame: the main loop may be busy answering a long COMMAND while the next one arrives. */
#define RX_RING_SIZE 2048u

/* hal_now_ms's state: TIM2's count when last read, and microseconds not yet counted as a millisecond. */
static uint32_t last_timer_us;
static uint32_t pending_us;
static uint32_t now_ms;

static volatile uint8_t rx_ring[RX_RING_SIZE];
static volatile uint32_t rx_head; /* written only by the interrupt */
static volatile uint32_t rx_tail; /* written only by the main loop */
static volatile uint32_t rx_dropped;

/* Rising edges of the e-stop input: counted by the interrupt only; the main loop remembers how many it
 * has seen, so no edge is lost between its read and a clear. */
static volatile uint32_t estop_edges;
static uint32_t estop_edges_seen;

/* SysTick interrupts taken, and their count when the main loop last polled. */
static volatile uint32_t systick_count;
static uint32_t polled_at_tick;

static volatile bool drivers_enabled; /* read back by tests/test_firmware_qemu.py through QEMU */

/* -- set-up -------------------------------------------------------------------------------------- */

static void gpio_set_mode(uint32_t base, uint32_t pin, uint32_t mode)
{
    GPIO_MODER(base) = (GPIO_MODER(base) & ~(3u << (2u * pin))) | (mode << (2u * pin));
}

static void drivers_pin_write(bool enabled)
{
    /* BSRR: the low half sets a pin, the high half resets it; one write, no read-modify-write race. */
    GPIO_BSRR(GPIOB_BASE) = enabled ? (1u << (DRIVERS_ENABLE_PIN + 16u)) : (1u << DRIVERS_ENABLE_PIN);
}

static void drivers_pin_init(void)
{
    drivers_pin_write(false); /* the level first, then the pin an output: no glitch that enables them */
    gpio_set_mode(GPIOB_BASE, DRIVERS_ENABLE_PIN, GPIO_MODE_OUTPUT);
}

/* PA1 an input with its pull-up, and EXTI1 on its rising edge (the chain opening). */
static void estop_input_init(void)
{
    gpio_set_mode(GPIOA_BASE, ESTOP_INPUT_PIN, GPIO_MODE_INPUT);
    uint32_t pull_shift = 2u * ESTOP_INPUT_PIN;
    GPIO_PUPDR(GPIOA_BASE) = (GPIO_PUPDR(GPIOA_BASE) & ~(3u << pull_shift)) | (GPIO_PULL_UP << pull_shift);
    uint32_t line_shift = 4u * (ESTOP_INPUT_PIN % 4u);
    uint32_t exticr = SYSCFG_EXTICR(ESTOP_INPUT_PIN / 4u) & ~(0xFu << line_shift);
    SYSCFG_EXTICR(ESTOP_INPUT_PIN / 4u) = exticr | (SYSCFG_EXTI_PORT_A << line_shift);
    EXTI_RTSR |= 1u << ESTOP_INPUT_PIN;
    EXTI_FTSR &= ~(1u << ESTOP_INPUT_PIN);
    EXTI_PR = 1u << ESTOP_INPUT_PIN; /* nothing stale from before the set-up */
    EXTI_IMR |= 1u << ESTOP_INPUT_PIN;
    NVIC_ISER(EXTI1_IRQN / 32u) = 1u << (EXTI1_IRQN % 32u);
}

static void usart1_init(void)
{
    gpio_set_mode(GPIOA_BASE, USART1_TX_PIN, GPIO_MODE_AF);
    gpio_set_mode(GPIOA_BASE, USART1_RX_PIN, GPIO_MODE_AF);
    /* AFRH holds pins 8..15, four bits each. */
    uint32_t tx_shift = 4u * (USART1_TX_PIN - 8u);
    uint32_t rx_shift = 4u * (USART1_RX_PIN - 8u);
    uint32_t afrh = GPIO_AFRH(GPIOA_BASE) & ~((0xFu << tx_shift) | (0xFu << rx_shift));
    GPIO_AFRH(GPIOA_BASE) = afrh | (GPIO_AF7_USART1 << tx_shift) | (GPIO_AF7_USART1 << rx_shift);

    /* With 16x oversampling BRR holds USARTDIV in 12.4 fixed point, i.e. APB2 / baud rounded. */
    USART1_BRR = (APB2_HZ + SERIAL_BAUD / 2u) / SERIAL_BAUD;
    USART1_CR1 = USART_CR1_UE | USART_CR1_TE | USART_CR1_RE | USART_CR1_RXNEIE;
    NVIC_ISER(USART1_IRQN / 32u) = 1u << (USART1_IRQN % 32u);
}

/* TIM2 counts microseconds from 0 to 2^32 - 1 and wraps: nothing to service, no interrupt. */
static void microsecond_timer_init(void)
{
    TIM2_PSC = TIM2_CLOCK_HZ / 1000000u - 1u;
    TIM2_ARR = 0xFFFFFFFFu;
    TIM2_EGR = TIM_EGR_UG; /* the prescaler is buffered: load it now, not at the first wrap */
    TIM2_CR1 = TIM_CR1_CEN;
    last_timer_us = TIM2_CNT;
}

static void systick_init(void)
{
    SYST_RVR = SYSCLK_HZ / STEP_TICK_HZ - 1u;
    SYST_CVR = 0u;
    SYST_CSR = SYST_CSR_ENABLE | SYST_CSR_TICKINT | SYST_CSR_CLKSOURCE_CPU;
}

void board_init(void)
{
    RCC_AHB1ENR |= RCC_AHB1ENR_GPIOAEN | RCC_AHB1ENR_GPIOBEN | RCC_AHB1ENR_GPIOCEN;
    RCC_APB1ENR |= RCC_APB1ENR_TIM2EN;
    RCC_APB2ENR |= RCC_APB2ENR_USART1EN | RCC_APB2ENR_SYSCFGEN;
    (void)RCC_APB2ENR; /* RM0090: wait a bus cycle after enabling a peripheral's clock before using it */
    drivers_pin_init();
    estop_input_init();
    microsecond_timer_init();
    steppers_init();
    usart1_init();
    systick_init();
}

void board_drivers_off(void)
{
    drivers_pin_write(false);
}

/* -- interrupts ------------------------------------------------------------------------------------ */

/* The step tick; taking the interrupt also wakes the main loop's wfi. */
void board_systick_handler(void)
{
    steppers_tick();
    systick_count = systick_count + 1u;
}

void board_usart1_handler(void)
{
    /* Reading SR then DR clears RXNE and an overrun alike; a byte that finds the ring full is dropped
     * (the frame it belonged to then fails its CRC, and the host retransmits). */
    while (USART1_SR & (USART_SR_RXNE | USART_SR_ORE)) {
        uint8_t byte = (uint8_t)USART1_DR;
        uint32_t head = rx_head;
        if (head - rx_tail < RX_RING_SIZE) {
            rx_ring[head % RX_RING_SIZE] = byte;
            rx_head = head + 1u;
        } else {
            rx_dropped++;
        }
    }
}

/* The e-stop chain opened: ENABLE off now, without waiting for the main loop (which latches the e-stop
 * at its next poll and keeps ENABLE off until ESTOP_CLEAR). */
void board_exti1_handler(void)
{
    if (EXTI_PR & (1u << ESTOP_INPUT_PIN)) {
        EXTI_PR = 1u << ESTOP_INPUT_PIN;
        drivers_pin_write(false);
        steppers_enable(false);
        estop_edges = estop_edges + 1u;
    }
}

bool board_work_pending(void)
{
    return rx_head != rx_tail || estop_edges != estop_edges_seen ||
           systick_count - polled_at_tick >= STEP_TICK_HZ / 1000u;
}

void board_polling(void)
{
    polled_at_tick = systick_count;
}

/* -- hal.h ------------------------------------------------------------------------------------------ */

/* Called from the main loop only (fw_poll, fw_init), at least every millisecond or so; the counter's
 * difference is right across its wrap as long as calls are less than 71 minutes apart. */
uint32_t hal_now_ms(void)
{
    uint32_t timer_us = TIM2_CNT;
    pending_us += timer_us - last_timer_us;
    last_timer_us = timer_us;
    now_ms += pending_us / MICROSECONDS_PER_MS;
    pending_us %= MICROSECONDS_PER_MS;
    return now_ms;
}

size_t hal_serial_read(uint8_t *buf, size_t max_len)
{
    uint32_t tail = rx_tail;
    uint32_t head = rx_head; /* read once: bytes arriving meanwhile wait for the next call */
    size_t n = 0;
    while (tail != head && n < max_len) {
        buf[n++] = rx_ring[tail % RX_RING_SIZE];
        tail++;
    }
    rx_tail = tail;
    return n;
}

void hal_serial_write(const uint8_t *data, size_t len)
{
    for (size_t i = 0; i < len; i++) {
        while (!(USART1_SR & USART_SR_TXE)) {
        }
        USART1_DR = data[i];
    }
}

void hal_drivers_enable(bool enabled)
{
    drivers_enabled = enabled;
    steppers_enable(enabled);
    drivers_pin_write(enabled);
}

bool hal_estop_input(void)
{
    uint32_t edges = estop_edges;
    bool opened = edges != estop_edges_seen;
    estop_edges_seen = edges;
    return opened || (GPIO_IDR(GPIOA_BASE) & (1u << ESTOP_INPUT_PIN)) != 0u;
}
