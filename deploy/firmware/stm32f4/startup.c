/*
 * Startup for the STM32F405: the vector table, and the reset handler that enables the FPU, copies .data
 * from flash, zeroes .bss and calls main(). The symbols come from stm32f405.ld.
 */
#include <stdint.h>

#include "board.h"
#include "regs.h"

/* 16 Cortex-M4 system exceptions, then the STM32F405's 82 interrupt lines (the last is the FPU's). */
#define SYSTEM_EXCEPTIONS 16u
#define IRQ_LINES 82u

typedef void (*vector_fn)(void);

extern uint32_t _sidata; /* .data's initial values, in flash */
extern uint32_t _sdata, _edata;
extern uint32_t _sbss, _ebss;
extern uint32_t _estack; /* top of SRAM: the initial main stack pointer */

int main(void);
void reset_handler(void);

/* The core computes in float and the compiler is told the FPU exists (-mfloat-abi=hard): it must be
 * enabled before any code that may touch an FPU register runs, or the first such instruction faults. */
static void enable_fpu(void)
{
    SCB_CPACR |= SCB_CPACR_FPU_FULL_ACCESS;
    __asm__ volatile("dsb\n\tisb" ::: "memory");
}

/* Word loops written out here: this runs before .data and .bss exist, so nothing it calls may use them
 * (the Makefile builds the port with -fno-tree-loop-distribute-patterns, so gcc does not turn these
 * loops back into memcpy/memset calls: there is no libc). */
static void init_memory(void)
{
    const uint32_t *src = &_sidata;
    for (uint32_t *dst = &_sdata; dst < &_edata;) {
        *dst++ = *src++;
    }
    for (uint32_t *dst = &_sbss; dst < &_ebss;) {
        *dst++ = 0u;
    }
}

void reset_handler(void)
{
    enable_fpu();
    init_memory();
    (void)main();
    for (;;) { /* main never returns; if it did, stay here rather than run off into flash */
        __asm__ volatile("wfi");
    }
}

/* Any fault (a bad access, an undefined instruction, an IRQ whose vector is left 0 below) ends here:
 * the motors must not keep running on a controller that has stopped listening, so cut the drivers and
 * halt. The host's link then sees silence and reports the controller lost. */
static void fault_handler(void)
{
    board_drivers_off();
    for (;;) {
        __asm__ volatile("wfi");
    }
}

/* Only SysTick, EXTI1 and USART1 are enabled; every other line stays masked in the NVIC, so its vector is 0. */
__attribute__((section(".isr_vector"), used))
static const vector_fn vector_table[SYSTEM_EXCEPTIONS + IRQ_LINES] = {
    [0] = (vector_fn)(uintptr_t)&_estack, /* not a handler: the initial stack pointer the core loads */
    [1] = reset_handler,
    [2] = fault_handler,  /* NMI */
    [3] = fault_handler,  /* HardFault (MemManage, BusFault and UsageFault escalate to it: not enabled) */
    [4] = fault_handler,  /* MemManage */
    [5] = fault_handler,  /* BusFault */
    [6] = fault_handler,  /* UsageFault */
    [11] = fault_handler, /* SVCall: unused */
    [14] = fault_handler, /* PendSV: unused */
    [15] = board_systick_handler,
    [SYSTEM_EXCEPTIONS + EXTI1_IRQN] = board_exti1_handler,
    [SYSTEM_EXCEPTIONS + USART1_IRQN] = board_usart1_handler,
};
