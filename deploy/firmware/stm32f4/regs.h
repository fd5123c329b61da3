/*
 * The few STM32F405 and Cortex-M4 registers this port touches, from the reference manual (RM0090) and
 * the Cortex-M4 generic user guide. Written out by hand on purpose: no vendor SDK or CMSIS is needed to
 * build the firmware, and every register used is visible here.
 */
#ifndef CLOTHD_FW_STM32F4_REGS_H
#define CLOTHD_FW_STM32F4_REGS_H

#include <stdint.h>

#define REG32(addr) (*(volatile uint32_t *)(uintptr_t)(addr))

/* -- RCC: clock enables (RM0090 6.3) ------------------------------------------------------------- */
#define RCC_BASE 0x40023800u
#define RCC_AHB1ENR REG32(RCC_BASE + 0x30u)
#define RCC_APB1ENR REG32(RCC_BASE + 0x40u)
#define RCC_APB2ENR REG32(RCC_BASE + 0x44u)
#define RCC_AHB1ENR_GPIOAEN (1u << 0)
#define RCC_AHB1ENR_GPIOBEN (1u << 1)
#define RCC_AHB1ENR_GPIOCEN (1u << 2)
#define RCC_APB1ENR_TIM2EN (1u << 0)
#define RCC_APB2ENR_USART1EN (1u << 4)
#define RCC_APB2ENR_SYSCFGEN (1u << 14)

/* -- TIM2: a 32-bit general-purpose timer on APB1 (RM0090 18.4) ------------------------------------ */
#define TIM2_BASE 0x40000000u
#define TIM2_CR1 REG32(TIM2_BASE + 0x00u)
#define TIM2_EGR REG32(TIM2_BASE + 0x14u)
#define TIM2_CNT REG32(TIM2_BASE + 0x24u)
#define TIM2_PSC REG32(TIM2_BASE + 0x28u)
#define TIM2_ARR REG32(TIM2_BASE + 0x2Cu)
#define TIM_CR1_CEN (1u << 0)
#define TIM_EGR_UG (1u << 0) /* update event: loads the (buffered) prescaler */

/* -- GPIO (RM0090 8.4) ------------------------------------------------------------------------------ */
#define GPIOA_BASE 0x40020000u
#define GPIOB_BASE 0x40020400u
#define GPIOC_BASE 0x40020800u
#define GPIO_MODER(base) REG32((base) + 0x00u)
#define GPIO_PUPDR(base) REG32((base) + 0x0Cu)
#define GPIO_IDR(base) REG32((base) + 0x10u)
#define GPIO_AFRH(base) REG32((base) + 0x24u)
#define GPIO_BSRR(base) REG32((base) + 0x18u)
#define GPIO_MODE_INPUT 0u
#define GPIO_MODE_OUTPUT 1u
#define GPIO_MODE_AF 2u
#define GPIO_AF7_USART1 7u
#define GPIO_PULL_UP 1u

/* -- SYSCFG: which port's pin drives each EXTI line (RM0090 9.2) ---------------------------------- */
#define SYSCFG_BASE 0x40013800u
#define SYSCFG_EXTICR(n) REG32(SYSCFG_BASE + 0x08u + 4u * (n)) /* lines 4n..4n+3, four bits each */
#define SYSCFG_EXTI_PORT_A 0u

/* -- EXTI: edge detection on the GPIO lines (RM0090 12.3) ----------------------------------------- */
#define EXTI_BASE 0x40013C00u
#define EXTI_IMR REG32(EXTI_BASE + 0x00u)
#define EXTI_RTSR REG32(EXTI_BASE + 0x08u)
#define EXTI_FTSR REG32(EXTI_BASE + 0x0Cu)
#define EXTI_PR REG32(EXTI_BASE + 0x14u) /* pending: write 1 to clear */
#define EXTI1_IRQN 7u

/* -- USART1 on APB2 (RM0090 30.6) ---------------------------------------------------------------- */
#define USART1_BASE 0x40011000u
#define USART1_SR REG32(USART1_BASE + 0x00u)
#define USART1_DR REG32(USART1_BASE + 0x04u)
#define USART1_BRR REG32(USART1_BASE + 0x08u)
#define USART1_CR1 REG32(USART1_BASE + 0x0Cu)
#define USART_SR_ORE (1u << 3)
#define USART_SR_RXNE (1u << 5)
#define USART_SR_TXE (1u << 7)
#define USART_CR1_RE (1u << 2)
#define USART_CR1_TE (1u << 3)
#define USART_CR1_RXNEIE (1u << 5)
#define USART_CR1_UE (1u << 13)
#define USART1_IRQN 37u

/* -- Cortex-M4 system control space -------------------------------------------------------------- */
#define SYST_CSR REG32(0xE000E010u) /* SysTick control and status */
#define SYST_RVR REG32(0xE000E014u) /* reload value */
#define SYST_CVR REG32(0xE000E018u) /* current value */
#define SYST_CSR_ENABLE (1u << 0)
#define SYST_CSR_TICKINT (1u << 1)
#define SYST_CSR_CLKSOURCE_CPU (1u << 2)

#define NVIC_ISER(n) REG32(0xE000E100u + 4u * (n)) /* interrupt set-enable, 32 IRQs per register */
#define SCB_CPACR REG32(0xE000ED88u)              /* coprocessor access: CP10 and CP11 are the FPU */
#define SCB_CPACR_FPU_FULL_ACCESS (0xFu << 20)

#endif
