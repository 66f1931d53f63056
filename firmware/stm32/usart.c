/* Host link: USART with an RX interrupt into a ring buffer and a TX ring drained from both
 * the TXE interrupt (real board) and the main loop (QEMU's USART model raises no TXE
 * interrupt), with interrupts masked so the two never race. */
#include "../core/board.h"
#include "regs.h"
#include "stm32.h"

#define RX_SIZE 512u /* > 2 frames: the main loop may be busy refilling the DAC for ~1 ms */
#define TX_SIZE 2048u

static volatile uint8_t rx_ring[RX_SIZE];
static volatile uint32_t rx_head, rx_tail;
static uint8_t tx_ring[TX_SIZE];
static volatile uint32_t tx_head, tx_tail;

void usart_init(void)
{
#if defined(BOARD_NUCLEO_F446RE)
    rcc_enable(&RCC_AHB1ENR, 1u);         /* GPIOA (errata-safe: before its first access) */
    rcc_enable(&RCC_APB1ENR, 1u << 17);   /* USART2 */
    GPIO_MODER(GPIOA_BASE) = (GPIO_MODER(GPIOA_BASE) & ~(0xFu << 4)) | (0xAu << 4); /* AF */
    GPIO_AFRL(GPIOA_BASE) = (GPIO_AFRL(GPIOA_BASE) & ~(0xFFu << 8)) | (0x77u << 8);  /* AF7 */
#else
    rcc_enable(&RCC_APB2ENR, 1u << 4); /* USART1 (ignored by QEMU, needed on silicon) */
#endif
    USART_BRR(HOST_USART_BASE) = (HOST_USART_PCLK + HOST_BAUD / 2u) / HOST_BAUD;
    USART_CR1(HOST_USART_BASE) = USART_CR1_UE | USART_CR1_TE | USART_CR1_RE | USART_CR1_RXNEIE;
    NVIC_ISER(HOST_USART_IRQ / 32) = 1u << (HOST_USART_IRQ % 32);
}

static void tx_drain_locked(void)
{
    while (tx_head != tx_tail && (USART_SR(HOST_USART_BASE) & USART_SR_TXE)) {
        USART_DR(HOST_USART_BASE) = tx_ring[tx_tail];
        tx_tail = (tx_tail + 1u) % TX_SIZE;
    }
    uint32_t cr1 = USART_CR1(HOST_USART_BASE);
    USART_CR1(HOST_USART_BASE) =
        tx_head != tx_tail ? (cr1 | USART_CR1_TXEIE) : (cr1 & ~USART_CR1_TXEIE);
}

static void host_usart_irq(void)
{
    uint32_t sr = USART_SR(HOST_USART_BASE);
    if (sr & (USART_SR_RXNE | USART_SR_ORE)) {
        uint8_t b = (uint8_t)USART_DR(HOST_USART_BASE); /* also clears ORE */
        uint32_t next = (rx_head + 1u) % RX_SIZE;
        if (next != rx_tail) {
            rx_ring[rx_head] = b;
            rx_head = next;
        } /* else dropped: the frame will fail its checksum and be reported as garbage */
    }
    tx_drain_locked();
}

#if defined(BOARD_NUCLEO_F446RE)
void USART2_IRQHandler(void) { host_usart_irq(); }
void USART1_IRQHandler(void) { HardFault_Handler(); }
#else
void USART1_IRQHandler(void) { host_usart_irq(); }
void USART2_IRQHandler(void) { HardFault_Handler(); }
#endif

size_t usart_read(uint8_t *buf, size_t cap)
{
    size_t n = 0;
    while (n < cap && rx_tail != rx_head) {
        buf[n++] = rx_ring[rx_tail];
        rx_tail = (rx_tail + 1u) % RX_SIZE;
    }
    return n;
}

bool usart_rx_pending(void)
{
    return rx_tail != rx_head;
}

void usart_write(const char *data, size_t len)
{
    irq_disable();
    for (size_t i = 0; i < len; i++) {
        uint32_t next = (tx_head + 1u) % TX_SIZE;
        if (next == tx_tail) {
            break; /* host not reading: drop rather than stall the DAC refill */
        }
        tx_ring[tx_head] = (uint8_t)data[i];
        tx_head = next;
    }
    tx_drain_locked();
    irq_enable();
}

void usart_pump(void)
{
    irq_disable();
    tx_drain_locked();
    irq_enable();
}

void board_tx(const char *data, size_t len)
{
    usart_write(data, len);
}
