//! USART1 buffers: the receive interrupt moves each byte into [`RX`]; the board's `write`
//! queues whole blocks into [`TX`], which the transmit-empty interrupt (and the main loop, in
//! case the interrupt is not raised) drains. Both queues are shared with the interrupt handler
//! through critical sections (single core: interrupts off).

use crate::hw;
use core::cell::RefCell;
use cortex_m::interrupt::{self, Mutex};
use heapless::Deque;

/// Receive buffer: larger than the protocol's receive window (192 bytes in flight).
pub const RX_CAPACITY: usize = 512;
/// Transmit buffer: several response blocks (64 bytes each at most).
pub const TX_CAPACITY: usize = 1024;

/// Bytes received, not yet given to the core.
pub static RX: Mutex<RefCell<Deque<u8, RX_CAPACITY>>> = Mutex::new(RefCell::new(Deque::new()));
/// Bytes for the host, not yet written to the USART.
pub static TX: Mutex<RefCell<Deque<u8, TX_CAPACITY>>> = Mutex::new(RefCell::new(Deque::new()));
/// Received bytes dropped because [`RX`] was full or the USART overran.
pub static RX_DROPPED: Mutex<RefCell<u32>> = Mutex::new(RefCell::new(0));

/// The USART1 interrupt: take the received byte, feed the transmitter.
pub fn on_interrupt() {
    interrupt::free(|cs| {
        let sr = hw::uart_status();
        if sr & (hw::SR_RXNE | hw::SR_ORE) != 0 {
            let byte = hw::uart_read();
            let mut dropped = RX_DROPPED.borrow(cs).borrow_mut();
            if sr & hw::SR_ORE != 0 {
                *dropped = dropped.saturating_add(1);
            }
            if sr & hw::SR_RXNE != 0 && RX.borrow(cs).borrow_mut().push_back(byte).is_err() {
                *dropped = dropped.saturating_add(1);
            }
        }
        if sr & hw::SR_TXE != 0 && hw::uart_tx_interrupt_on() {
            pump_tx(&mut TX.borrow(cs).borrow_mut());
        }
    });
}

/// Writes queued bytes while the USART takes them; turns the transmit interrupt off once the
/// queue is empty.
fn pump_tx(tx: &mut Deque<u8, TX_CAPACITY>) {
    while hw::uart_status() & hw::SR_TXE != 0 {
        match tx.pop_front() {
            Some(b) => hw::uart_write(b),
            None => {
                hw::uart_tx_interrupt(false);
                return;
            }
        }
    }
}

/// Queues `bytes` for the host. When the queue is full this waits for the USART (a response
/// burst larger than the queue), so no byte is ever dropped.
pub fn send(mut bytes: &[u8]) {
    while !bytes.is_empty() {
        interrupt::free(|cs| {
            let mut tx = TX.borrow(cs).borrow_mut();
            while let Some((&b, rest)) = bytes.split_first() {
                if tx.push_back(b).is_err() {
                    break;
                }
                bytes = rest;
            }
            pump_tx(&mut tx);
            if !tx.is_empty() {
                hw::uart_tx_interrupt(true);
            }
        });
    }
}

/// Moves queued output on (for when the transmit interrupt is not raised); true if output is
/// still waiting.
pub fn poll_tx() -> bool {
    interrupt::free(|cs| {
        let mut tx = TX.borrow(cs).borrow_mut();
        pump_tx(&mut tx);
        !tx.is_empty()
    })
}

/// Takes up to `buf.len()` received bytes; returns how many.
pub fn take_rx(buf: &mut [u8]) -> usize {
    interrupt::free(|cs| {
        let mut rx = RX.borrow(cs).borrow_mut();
        let mut n = 0;
        while n < buf.len() {
            match rx.pop_front() {
                Some(b) => {
                    buf[n] = b;
                    n += 1;
                }
                None => break,
            }
        }
        n
    })
}
