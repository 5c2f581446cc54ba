//! The polar cell's RP2040 firmware: `cell_firmware_core` on a Raspberry Pi Pico.
//!
//! Everything the MCU decides is in `cell_firmware_core` (host-tested, and run by the
//! `mcu_emulator`); this crate only connects it to the chip:
//!
//! * **UART0** (GP16 TX, GP17 RX, 921,600 baud, 8N1) carries the wire protocol
//!   (`nodes/cell_protocol/PROTOCOL.md`). Received bytes are moved to a ring by the UART's
//!   interrupt, so a frame being decoded never overruns the 32-byte FIFO.
//! * **USB** is a composite device with two CDC-ACM serial ports: the first carries the
//!   same wire protocol (`/dev/ttyACM0` on Linux), the second seed 001's position lines
//!   `X:<steps>,Y:<steps>,Z:<steps>` for its PC plotter, sent at most every 10 ms while the
//!   position changes and always once it stops. The protocol's replies go where the host's
//!   bytes last came from, UART0 or USB. USB is polled by the main loop; the driver's
//!   critical sections mask every interrupt but the step timer's ([`AllButSteps`]).
//! * **Start switch** (bench rig, GP15 to ground): pressed for 20 ms on an idle MCU that no
//!   host has configured, it plays seed 001's own bench program (`cell_firmware_core::
//!   seed_program`), as the seed's Pico did.
//! * **Step timing** comes from the 1 MHz hardware timer, which is the MCU clock of the
//!   protocol: an edge at clock `c` reaches its pins when the timer reads `c`. The main loop
//!   runs the generator [`LEAD_TICKS`] ahead of the timer into an output queue, and the
//!   timer's ALARM0 interrupt (highest priority) writes each edge when its tick comes. The
//!   link (clock replies, timeouts) runs on the timer itself; the state reports carry the
//!   generator's clock with the positions it has reached, so both are exact. The register
//!   writes of each edge are computed by the generator too, and the alarm fires
//!   [`ALARM_EARLY_TICKS`] before the edge's tick: the interrupt then only waits for the
//!   tick and writes, so every edge leaves the same few cycles after its tick. What the queue
//!   still holds at an emergency stop is dropped and taken back from the positions.
//! * **Outputs** per axis from the build profile (`profile.rs`): step/dir drivers with a
//!   shared enable for the cell, or four coil inputs per 28BYJ-48 for seed 001's bench rig;
//!   the screw's pin on GP12 and its speed as PWM duty on GP13.
//!
//! From power-up the drivers are disabled and the coils released until a host configures the
//! MCU (or the bench rig's start switch starts seed 001's program): a board waiting hours for
//! its host holds no current in the motors. Faults stop the outputs at once (edges dropped, a
//! pulse already begun left to end, drivers disabled or coils released, pin closed, screw 0)
//! and are latched by the core until the host resets it.
//!
//! No ROM calls: the clocks, UART and timer are set up through `rp2040-hal`, whose start-up
//! does not call the boot ROM, so the same image runs on a Pico and in `rp2040js` (which
//! has no boot ROM; `tests/firmware/`).

#![no_std]
#![no_main]

mod profile;

use core::cell::{RefCell, UnsafeCell};
use core::sync::atomic::{AtomicBool, AtomicU32, Ordering};

use cell_firmware_core::outputs::{EdgeWrites, Outputs};
use cell_firmware_core::{Endpoint, Machine, MachineConfig, StepEdge};
use cell_protocol::message::{FaultCode, Mode};
use cell_protocol::{LinkOptions, MAX_WIRE_FRAME};
use critical_section::Mutex;
use heapless::spsc::{Consumer, Producer, Queue};
use rp2040_hal as hal;
use rp2040_hal::fugit::RateExtU32;
use rp2040_hal::pac::{self, interrupt};
use usb_device::class_prelude::UsbBusAllocator;
use usb_device::prelude::{StringDescriptors, UsbDeviceBuilder, UsbVidPid};
use usbd_serial::SerialPort;

/// The second-stage bootloader for the Pico's W25Q080-compatible flash.
#[link_section = ".boot2"]
#[used]
pub static BOOT2: [u8; 256] = rp2040_boot2::BOOT_LOADER_W25Q080;

/// The Pico's crystal.
const XTAL_HZ: u32 = 12_000_000;
/// The MCU clock: the hardware timer's 1 µs tick.
const TIMER_HZ: u32 = 1_000_000;
/// How far ahead of the pins the edges are generated (ticks): longer than the main loop's
/// period plus its worst pass (see `MAIN_MAX_CYCLES`), short enough that a hold reacts
/// promptly and a stop drops little.
pub const LEAD_TICKS: u64 = 2_000;
/// The main loop's wake-up period when no frame arrives (ticks).
const LOOP_PERIOD_TICKS: u32 = 250;
/// Most ticks generated between two looks at the receive ring, so that an emergency stop
/// waits for little generation: at full feed the generator jumps from pulse to pulse (500
/// ticks cost little; shorter chunks cost the top step rates their margin), while a hold's
/// σ ramp walks every tick at some 100 cycles each (100 ticks, under 0.1 ms).
const GENERATE_CHUNK_TICKS: u64 = 500;
const RAMP_CHUNK_TICKS: u64 = 100;
/// How early the output alarm fires (ticks): the interrupt's entry and bookkeeping happen
/// before the tick, the write itself right at it. An output due sooner than this after the
/// one just written is waited for without leaving the interrupt.
const ALARM_EARLY_TICKS: u64 = 2;
/// Step pulse width (ticks): step/dir drivers need 1–2 µs high; it ends 2–3 µs after the edge.
const PULSE_TICKS: u64 = 3;
/// Direction set-up before a step that changes it, in cycles: 650 ns at 125 MHz (a DRV8825's
/// minimum; an A4988 wants 200 ns, a TMC2209 20 ns). Direction pins are written when the
/// interrupt begins to wait for the step's tick, normally most of [`ALARM_EARLY_TICKS`]
/// before it; the step waits for the rest only when less is left.
const DIR_SETUP_CYCLES: u32 = 82;
/// A screw output due at the same tick as a step edge goes out after it, a tick or two
/// late; that is nothing to material flow (the host's own commands are ms apart), so only
/// more than this counts as late.
const SCREW_LATE_TICKS: i32 = 10;
/// PWM top of the screw's speed output: 125 MHz / 10,000 = 12.5 kHz.
const PWM_TOP: u16 = 9_999;

/// USB identity: pid.codes' VID and its test PID 0x0001 (for development; a product
/// would take its own PID from pid.codes).
const USB_VID_PID: UsbVidPid = UsbVidPid(0x1209, 0x0001);
/// USB packets (64 bytes) taken per main-loop pass: a host's burst (the queue filled at the
/// start of a print) read in one pass held the step generator for 1.9 ms of its 2 ms lead.
/// Four per 250 µs pass still take 1 MB/s, ten times what a print needs.
const USB_PACKETS_PER_PASS: usize = 4;
/// Position lines at most this often while the position changes (ticks).
const LINES_PERIOD_TICKS: u64 = 10_000;
/// The start switch must read pressed this long (ticks) before it counts: contact bounce.
const SWITCH_DEBOUNCE_TICKS: u64 = 20_000;
/// Seed 001's program starts this long after the switch counts (ticks on the plan clock).
const SEED_PROGRAM_LEAD_TICKS: u64 = 10_000;

const LINK_WINDOW: usize = 32;
/// Segments the MCU holds: 1,024 cover more than the 2 s horizon at the cell's densest plans
/// (circles about the centre at 6 rad/s, some 300 segments a second); 256 did not, and the
/// bridge held the machine on the path waiting for room.
const SEGMENT_QUEUE: usize = 1024;
const SCREW_QUEUE: usize = 512;
const OUTPUT_QUEUE: usize = 512;
const RX_RING: usize = 2048;
/// Replies waiting for UART0's transmit FIFO (32 bytes) to take them.
const UART_TX: usize = 1024;

type McuEndpoint = Endpoint<LINK_WINDOW, SEGMENT_QUEUE, SCREW_QUEUE>;

/// What the ALARM0 interrupt writes to the pins when the timer reaches `clock`.
#[derive(Clone, Copy, Debug)]
enum Output {
    /// An edge and its register writes (computed by the generator).
    Step { edge: StepEdge, writes: EdgeWrites },
    Screw {
        clock: u64,
        /// PWM compare value (the division done by the generator, not in the interrupt).
        duty: u16,
        pin_open: bool,
    },
}

impl Output {
    fn clock(&self) -> u64 {
        match *self {
            Output::Step { edge, .. } => edge.clock,
            Output::Screw { clock, .. } => clock,
        }
    }
}

/// The pin writer, owned by the ALARM0 interrupt; the main loop takes it only to stop.
struct PinWriter {
    queue: Consumer<'static, Output>,
    /// Step pins high and the tick from which they go low.
    pulse: Option<(u32, u64)>,
}

static PIN_WRITER: Mutex<RefCell<Option<PinWriter>>> = Mutex::new(RefCell::new(None));

/// The pin writer, with every interrupt masked (PRIMASK), the step timer's too: the
/// critical section everything else uses ([`AllButSteps`]) leaves the timer running.
fn with_pin_writer<R>(f: impl FnOnce(&mut Option<PinWriter>) -> R) -> R {
    cortex_m::interrupt::free(|_| {
        // SAFETY: every interrupt is masked while the closure runs.
        let cs = unsafe { critical_section::CriticalSection::new() };
        f(&mut PIN_WRITER.borrow_ref_mut(cs))
    })
}

/// The `critical-section` implementation for everything but the pin writer (the HAL's USB
/// driver, `singleton!`): it masks every interrupt line *except* the step timer's in the NVIC,
/// so a critical section elsewhere — the USB driver copying a packet — never delays an edge.
/// Sound because the step timer's interrupt touches nothing such a section guards: only the
/// pin writer (guarded by [`with_pin_writer`]), its own registers and atomics. Single core.
struct AllButSteps;
critical_section::set_impl!(AllButSteps);

/// The NVIC lines [`AllButSteps`] may mask: all but TIMER_IRQ_0.
const MASKABLE_IRQS: u32 = !(1 << pac::Interrupt::TIMER_IRQ_0 as u32);

// SAFETY: acquire masks every maskable line that was enabled and returns which; release
// enables those again. Nested sections restore in order; no interrupt handler changes the
// NVIC's enables.
unsafe impl critical_section::Impl for AllButSteps {
    unsafe fn acquire() -> critical_section::RawRestoreState {
        // SAFETY: the NVIC's set/clear-enable registers; writes are single and atomic.
        let nvic = unsafe { &*cortex_m::peripheral::NVIC::PTR };
        let enabled = nvic.iser[0].read() & MASKABLE_IRQS;
        unsafe { nvic.icer[0].write(enabled) };
        cortex_m::asm::dsb();
        cortex_m::asm::isb();
        enabled
    }

    unsafe fn release(enabled: critical_section::RawRestoreState) {
        cortex_m::asm::dsb();
        // SAFETY: as above.
        let nvic = unsafe { &*cortex_m::peripheral::NVIC::PTR };
        unsafe { nvic.iser[0].write(enabled) };
    }
}

/// A value `main` hands to one interrupt before unmasking it, touched by that interrupt
/// alone from then on. No critical section: the UART's interrupt must never mask the step
/// timer's, or edges would wait for it.
struct InterruptOwned<T>(UnsafeCell<Option<T>>);

// SAFETY: written once by `main` while the owning interrupt is masked, then used only by
// that interrupt (which does not preempt itself).
unsafe impl<T: Send> Sync for InterruptOwned<T> {}

static RX: InterruptOwned<Producer<'static, u8>> = InterruptOwned(UnsafeCell::new(None));

/// Worst cycles spent in one ALARM0 interrupt (SysTick counts them), read by the
/// firmware-in-the-loop harness from RAM.
#[no_mangle]
pub static ISR_MAX_CYCLES: AtomicU32 = AtomicU32::new(0);
/// Worst cycles of one main-loop pass (bytes decoded, edges generated, frames sent) with the
/// outputs running from its start to its end: it must stay well inside [`LEAD_TICKS`]. A pass
/// that stops them (the queued edges taken back with every interrupt masked) or runs while
/// they are stopped has no edge to be late for, and is not counted.
#[no_mangle]
pub static MAIN_MAX_CYCLES: AtomicU32 = AtomicU32::new(0);
/// Edges written to the pins.
#[no_mangle]
pub static EDGES_OUTPUT: AtomicU32 = AtomicU32::new(0);
/// Bytes lost because the receive ring was full.
#[no_mangle]
pub static RX_OVERRUNS: AtomicU32 = AtomicU32::new(0);
/// Frames from the host that failed their CRC or framing, and NAKs sent for them (copied
/// from the endpoint's counters each pass).
#[no_mangle]
pub static BAD_FRAMES: AtomicU32 = AtomicU32::new(0);
#[no_mangle]
pub static NAKS_SENT: AtomicU32 = AtomicU32::new(0);
/// Bytes of the protocol that came over USB, and bytes sent back that way.
#[no_mangle]
pub static USB_LINK_BYTES_IN: AtomicU32 = AtomicU32::new(0);
#[no_mangle]
pub static USB_LINK_BYTES_OUT: AtomicU32 = AtomicU32::new(0);
/// Position lines sent on the second USB port.
#[no_mangle]
pub static POSITION_LINES: AtomicU32 = AtomicU32::new(0);
/// Times the start switch started seed 001's program.
#[no_mangle]
pub static SEED_PROGRAM_STARTS: AtomicU32 = AtomicU32::new(0);
/// Step edges written more than one tick after their own (the generator fell behind the
/// pins).
#[no_mangle]
pub static LATE_STEP_OUTPUTS: AtomicU32 = AtomicU32::new(0);
/// Screw outputs written more than [`SCREW_LATE_TICKS`] after their own.
#[no_mangle]
pub static LATE_SCREW_OUTPUTS: AtomicU32 = AtomicU32::new(0);

/// Add to a counter that one context alone writes (the M0+ has no atomic read-modify-write).
fn bump(counter: &AtomicU32, n: u32) {
    counter.store(
        counter.load(Ordering::Relaxed).wrapping_add(n),
        Ordering::Relaxed,
    );
}

fn timer() -> &'static pac::timer::RegisterBlock {
    // SAFETY: read-only counters and the alarm registers, which only this firmware uses.
    unsafe { &*pac::TIMER::ptr() }
}

fn sio() -> &'static pac::sio::RegisterBlock {
    // SAFETY: the SIO's set/clear/xor registers are single-write atomic.
    unsafe { &*pac::SIO::ptr() }
}

/// The 64-bit timer, read without the latching registers (safe from any context).
fn timer_now() -> u64 {
    let t = timer();
    loop {
        let hi = t.timerawh().read().bits();
        let lo = t.timerawl().read().bits();
        if t.timerawh().read().bits() == hi {
            return ((hi as u64) << 32) | lo as u64;
        }
    }
}

/// The screw's speed as the PWM compare value (full scale: always high).
fn screw_duty(millirpm: i32) -> u16 {
    (millirpm.clamp(0, profile::SCREW_FULL_SCALE_MILLIRPM) as u64 * (PWM_TOP as u64 + 1)
        / profile::SCREW_FULL_SCALE_MILLIRPM as u64) as u16
}

fn set_screw_outputs(duty: u16, pin_open: bool) {
    // SAFETY: the PWM slice's compare register; the slice was set up in `main`.
    let pwm = unsafe { &*pac::PWM::ptr() };
    pwm.ch(profile::SCREW_PWM_SLICE)
        .cc()
        .modify(|_, w| unsafe { w.b().bits(duty) });
    if pin_open {
        sio()
            .gpio_out_set()
            .write(|w| unsafe { w.bits(1 << profile::SCREW_PIN) });
    } else {
        sio()
            .gpio_out_clr()
            .write(|w| unsafe { w.bits(1 << profile::SCREW_PIN) });
    }
}

/// The low 32 bits of the timer: enough to wait for a tick less than 71 minutes away.
fn timer_low() -> u32 {
    timer().timerawl().read().bits()
}

/// Busy-wait until the timer reaches `tick` (at once if it has).
fn wait_for_tick(tick: u64) {
    let tick = tick as u32;
    while (tick.wrapping_sub(timer_low()) as i32) > 0 {}
}

fn count_if_late(tick: u64, allowed_ticks: i32, counter: &AtomicU32) {
    if timer_low().wrapping_sub(tick as u32) as i32 > allowed_ticks {
        bump(counter, 1);
    }
}

/// Queue the screw's outputs at the generator's clock if they changed (a full queue: tried
/// again after the next chunk).
fn sample_screw(
    machine: &Machine<SEGMENT_QUEUE, SCREW_QUEUE>,
    screw_output: &mut (i32, bool),
    to_pins: &mut Producer<'static, Output>,
) {
    let screw = (machine.screw_millirpm(), machine.pin_open());
    if screw != *screw_output && to_pins.ready() {
        let _ = to_pins.enqueue(Output::Screw {
            clock: machine.clock(),
            duty: screw_duty(screw.0),
            pin_open: screw.1,
        });
        *screw_output = screw;
    }
}

/// Write one output at its tick.
fn write_output(writer: &mut PinWriter, output: Output) {
    match output {
        Output::Step { edge, writes } => {
            if let Some((mask, high_until)) = writer.pulse {
                if mask & writes.step_set != 0 {
                    // An axis still high from its last pulse (edges running late, a burst
                    // of them due at once): end that pulse and keep the pin low as long, or
                    // the driver takes two steps for one; before the direction changes too
                    // (its hold time after that step).
                    wait_for_tick(high_until);
                    sio().gpio_out_clr().write(|r| unsafe { r.bits(mask) });
                    writer.pulse = None;
                    wait_for_tick(high_until + PULSE_TICKS);
                }
            }
            let direction_changed = writes.dir_set | writes.dir_clear != 0;
            let mut dir_written = 0;
            if direction_changed {
                sio()
                    .gpio_out_set()
                    .write(|r| unsafe { r.bits(writes.dir_set) });
                sio()
                    .gpio_out_clr()
                    .write(|r| unsafe { r.bits(writes.dir_clear) });
                dir_written = cortex_m::peripheral::SYST::get_current();
            }
            wait_for_tick(edge.clock);
            // Set-up counted in core cycles (SysTick counts down), normally long over by now.
            while direction_changed
                && dir_written.wrapping_sub(cortex_m::peripheral::SYST::get_current()) & 0x00FF_FFFF
                    < DIR_SETUP_CYCLES
            {}
            sio()
                .gpio_out_set()
                .write(|r| unsafe { r.bits(writes.step_set) });
            sio()
                .gpio_out_xor()
                .write(|r| unsafe { r.bits(writes.coil_toggle) });
            count_if_late(edge.clock, 1, &LATE_STEP_OUTPUTS);
            if writes.step_set != 0 {
                // High for its width from when it was written: a late edge's would otherwise
                // be over at once (below a driver's minimum).
                let mask = writer.pulse.map_or(0, |(m, _)| m) | writes.step_set;
                writer.pulse = Some((mask, edge.clock.max(timer_now()) + PULSE_TICKS));
            }
            bump(&EDGES_OUTPUT, 1);
        }
        Output::Screw {
            clock,
            duty,
            pin_open,
        } => {
            wait_for_tick(clock);
            set_screw_outputs(duty, pin_open);
            count_if_late(clock, SCREW_LATE_TICKS, &LATE_SCREW_OUTPUTS);
        }
    }
}

/// Write every output that is due, end step pulses whose width has passed, then arm ALARM0
/// [`ALARM_EARLY_TICKS`] before whichever comes next. Pulses end by the alarm too, not by
/// waiting in here, so an edge of another axis one tick later is still written on its tick.
#[interrupt]
fn TIMER_IRQ_0() {
    let entered = cortex_m::peripheral::SYST::get_current();
    timer().intr().write(|w| w.alarm_0().clear_bit_by_one());
    with_pin_writer(|writer| {
        let Some(writer) = writer.as_mut() else {
            return;
        };
        loop {
            let now = timer_now();
            if let Some((mask, high_until)) = writer.pulse {
                if now >= high_until {
                    sio().gpio_out_clr().write(|r| unsafe { r.bits(mask) });
                    writer.pulse = None;
                }
            }
            let next_due = writer.queue.peek().map(Output::clock);
            if let Some(due) = next_due {
                if due <= now + ALARM_EARLY_TICKS {
                    let Some(output) = writer.queue.dequeue() else {
                        break;
                    };
                    write_output(writer, output);
                    continue;
                }
            }
            let wake = match (next_due, writer.pulse) {
                (Some(due), Some((_, end))) => (due - ALARM_EARLY_TICKS).min(end),
                (Some(due), None) => due - ALARM_EARLY_TICKS,
                (None, Some((_, end))) => end,
                (None, None) => break,
            };
            timer().alarm0().write(|w| unsafe { w.bits(wake as u32) });
            // Armed for a time still ahead: done. Passed meanwhile: disarm and go round
            // again (an alarm only fires on an exact match).
            if wake > timer_now() {
                break;
            }
            timer().armed().write(|w| unsafe { w.bits(1) });
        }
    });
    // SysTick counts down from its reload value (24 bits, wraps every 134 ms at 125 MHz).
    let left = cortex_m::peripheral::SYST::get_current();
    let spent = entered.wrapping_sub(left) & 0x00FF_FFFF;
    if spent > ISR_MAX_CYCLES.load(Ordering::Relaxed) {
        ISR_MAX_CYCLES.store(spent, Ordering::Relaxed);
    }
}

/// Set by the interrupts that give the main loop work (its period, a received frame); the
/// step interrupt wakes the core from WFI too, tens of thousands of times a second at the
/// top rates, and a pass for each of those (USB polled, the generator run a few ticks on,
/// replies looked for) cost more than the steps themselves.
static MAIN_WORK: AtomicBool = AtomicBool::new(true);

/// The main loop's period.
#[interrupt]
fn TIMER_IRQ_1() {
    timer().intr().write(|w| w.alarm_1().clear_bit_by_one());
    MAIN_WORK.store(true, Ordering::Relaxed);
}

/// Move received bytes from the UART's FIFO to the ring.
#[interrupt]
fn UART0_IRQ() {
    // SAFETY: the data and flag registers; the main loop only transmits.
    let uart = unsafe { &*pac::UART0::ptr() };
    // SAFETY: this interrupt owns the producer (see `InterruptOwned`).
    let Some(rx) = (unsafe { &mut *RX.0.get() }).as_mut() else {
        return;
    };
    let mut frame_ended = false;
    while uart.uartfr().read().rxfe().bit_is_clear() {
        let byte = uart.uartdr().read().data().bits();
        if rx.enqueue(byte).is_err() {
            bump(&RX_OVERRUNS, 1);
        }
        frame_ended |= byte == 0;
    }
    // A pass when a frame is complete (its delimiter, 0), not for every few bytes of it:
    // at the line's full rate that was a pass per 4 bytes, all of the core's time.
    if frame_ended || rx.len() >= RX_RING / 2 {
        MAIN_WORK.store(true, Ordering::Relaxed);
    }
}

/// Hand the endpoint every byte UART0's interrupt has put in the ring, stamped with the
/// timer now; whether any came.
fn take_received(
    received: &mut Consumer<'static, u8>,
    endpoint: &mut McuEndpoint,
    bytes: &mut [u8; 64],
) -> bool {
    let mut any = false;
    loop {
        let mut n = 0;
        while n < bytes.len() {
            let Some(byte) = received.dequeue() else {
                break;
            };
            bytes[n] = byte;
            n += 1;
        }
        if n == 0 {
            return any;
        }
        any = true;
        endpoint.receive(&bytes[..n], timer_now());
    }
}

/// Bytes waiting for a serial line (UART0's FIFO or a USB port): whole frames or lines go
/// in only when they fit, so the line never carries half of one, and the line takes them
/// as it can, never waited for (a pass that waited for UART0 — 250 bytes of replies take
/// 2.7 ms at 921,600 baud — held the step generator back past its lead).
struct TxQueue<const N: usize>(heapless::Deque<u8, N>);

impl<const N: usize> TxQueue<N> {
    const fn new() -> Self {
        TxQueue(heapless::Deque::new())
    }

    fn free(&self) -> usize {
        N - self.0.len()
    }

    /// Queue all of `bytes`, or nothing if they do not fit.
    fn push(&mut self, bytes: &[u8]) -> bool {
        if bytes.len() > self.free() {
            return false;
        }
        for &byte in bytes {
            let _ = self.0.push_back(byte);
        }
        true
    }

    /// Queue the endpoint's frames while a whole frame still fits.
    fn fill(&mut self, endpoint: &mut McuEndpoint, now: u64, frame: &mut [u8; MAX_WIRE_FRAME]) {
        while self.free() >= MAX_WIRE_FRAME {
            let Some(len) = endpoint.poll_transmit(now, frame) else {
                break;
            };
            self.push(&frame[..len]);
        }
    }

    /// Hand a USB port what it takes now; returns the bytes it took.
    fn flush_usb<B: usb_device::bus::UsbBus>(&mut self, port: &mut SerialPort<'_, B>) -> usize {
        let mut sent = 0;
        while !self.0.is_empty() {
            let (head, _) = self.0.as_slices();
            match port.write(head) {
                Ok(n) if n > 0 => {
                    for _ in 0..n {
                        self.0.pop_front();
                    }
                    sent += n;
                }
                _ => break,
            }
        }
        sent
    }

    /// Move bytes into UART0's transmit FIFO while it has room.
    fn flush_uart(&mut self) {
        // SAFETY: the data and flag registers; the interrupt only receives.
        let uart = unsafe { &*pac::UART0::ptr() };
        while uart.uartfr().read().txff().bit_is_clear() {
            let Some(byte) = self.0.pop_front() else {
                break;
            };
            uart.uartdr().write(|w| unsafe { w.data().bits(byte) });
        }
    }
}

/// Where the protocol's replies go: where the host's bytes last came from.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Transport {
    Uart,
    Usb,
}

/// A nonce for the link session: the ring oscillator's jitter, one bit at a time.
fn nonce(rosc: &pac::ROSC) -> u32 {
    (0..32).fold(0, |n, _| {
        (n << 1) | rosc.randombit().read().randombit().bit() as u32
    })
}

/// Stop every output now: drop the queued edges (and take them back from the positions),
/// release the motors, close the pin, stop the screw. The output stage then follows the
/// pins again, not the edges it had computed.
fn stop_outputs(endpoint: &mut McuEndpoint, outputs: &mut Outputs) {
    with_pin_writer(|writer| {
        if let Some(writer) = writer.as_mut() {
            let queue = &mut writer.queue;
            endpoint.discard_edges(core::iter::from_fn(|| loop {
                match queue.dequeue()? {
                    Output::Step { edge, .. } => return Some(edge),
                    Output::Screw { .. } => continue,
                }
            }));
            // A pulse already begun runs its width (at most PULSE_TICKS + 1): its step is
            // counted in the positions, and cut short a driver could miss it.
            let step_pins = writer.pulse.take().map_or(0, |(mask, high_until)| {
                wait_for_tick(high_until);
                mask
            });
            outputs.resync(sio().gpio_out().read().bits());
            sio()
                .gpio_out_clr()
                .write(|w| unsafe { w.bits(outputs.coil_mask() | step_pins) });
        }
        timer().armed().write(|w| unsafe { w.bits(1) });
    });
    profile::disable_drivers();
    set_screw_outputs(0, false);
}

/// Outputs on once a host configured the MCU, and again after a reset cleared a fault:
/// drivers enabled, coils energised at the phase they were released in.
fn restart_outputs(outputs: &Outputs) {
    sio()
        .gpio_out_set()
        .write(|w| unsafe { w.bits(outputs.initial_levels() & outputs.coil_mask()) });
    profile::enable_drivers();
}

#[hal::entry]
fn main() -> ! {
    let mut pac = pac::Peripherals::take().unwrap();
    let mut core = pac::CorePeripherals::take().unwrap();
    let mut watchdog = hal::Watchdog::new(pac.WATCHDOG);
    let Ok(clocks) = hal::clocks::init_clocks_and_plls(
        XTAL_HZ,
        pac.XOSC,
        pac.CLOCKS,
        pac.PLL_SYS,
        pac.PLL_USB,
        &mut pac.RESETS,
        &mut watchdog,
    ) else {
        panic!("clocks");
    };
    let sio_hal = hal::Sio::new(pac.SIO);
    let pins = hal::gpio::Pins::new(
        pac.IO_BANK0,
        pac.PADS_BANK0,
        sio_hal.gpio_bank0,
        &mut pac.RESETS,
    );
    // The timer is the MCU clock; the watchdog's tick (set up with the clocks) drives it.
    let _timer = hal::Timer::new(pac.TIMER, &mut pac.RESETS, &clocks);

    // Outputs: the profile's pins as SIO outputs, at their initial levels.
    let initial_steps = [0i32; 3];
    let mut outputs = Outputs::new(profile::STAGES, initial_steps);
    // Coils released and drivers disabled until a host configures the MCU (or the start
    // switch starts seed 001's program): `restart_outputs` then energises them.
    profile::configure_pins(
        outputs.mask(),
        outputs.initial_levels() & !outputs.coil_mask(),
    );
    let mut pwm_slices = hal::pwm::Slices::new(pac.PWM, &mut pac.RESETS);
    let screw_pwm = &mut pwm_slices.pwm6;
    screw_pwm.set_top(PWM_TOP);
    screw_pwm.enable();
    let _screw_speed_pin = screw_pwm.channel_b.output_to(pins.gpio13);
    set_screw_outputs(0, false);

    // UART0 on GP16/GP17.
    let uart_pins = (
        pins.gpio16.into_function::<hal::gpio::FunctionUart>(),
        pins.gpio17.into_function::<hal::gpio::FunctionUart>(),
    );
    let Ok(mut uart) = hal::uart::UartPeripheral::new(pac.UART0, uart_pins, &mut pac.RESETS)
        .enable(
            hal::uart::UartConfig::new(
                921_600.Hz(),
                hal::uart::DataBits::Eight,
                None,
                hal::uart::StopBits::One,
            ),
            hal::Clock::freq(&clocks.peripheral_clock),
        )
    else {
        panic!("uart");
    };
    uart.enable_rx_interrupt();

    // USB: two CDC-ACM ports, the protocol's and the position lines'.
    let usb_bus: &'static UsbBusAllocator<hal::usb::UsbBus> = cortex_m::singleton!(
        : UsbBusAllocator<hal::usb::UsbBus> = UsbBusAllocator::new(hal::usb::UsbBus::new(
            pac.USBCTRL_REGS,
            pac.USBCTRL_DPRAM,
            clocks.usb_clock,
            true,
            &mut pac.RESETS,
        ))
    )
    .unwrap();
    let mut usb_link = SerialPort::new(usb_bus);
    let mut usb_lines = SerialPort::new(usb_bus);
    let Ok(builder) =
        UsbDeviceBuilder::new(usb_bus, USB_VID_PID).strings(&[StringDescriptors::default()
            .manufacturer("polar-cell")
            .product("polar cell MCU (link, position lines)")
            .serial_number("1")])
    else {
        panic!("usb strings");
    };
    let Ok(builder) = builder.composite_with_iads().max_packet_size_0(64) else {
        panic!("usb ep0");
    };
    let mut usb = builder.build();
    let mut usb_link_out = TxQueue::<1024>::new();
    let mut usb_lines_out = TxQueue::<256>::new();

    let outputs_queue = cortex_m::singleton!(: Queue<Output, OUTPUT_QUEUE> = Queue::new()).unwrap();
    let (mut to_pins, from_generator) = outputs_queue.split();
    let rx_ring = cortex_m::singleton!(: Queue<u8, RX_RING> = Queue::new()).unwrap();
    let (rx_producer, mut received) = rx_ring.split();
    with_pin_writer(|writer| {
        writer.replace(PinWriter {
            queue: from_generator,
            pulse: None,
        })
    });
    // SAFETY: UART0's interrupt, the producer's owner, is still masked.
    unsafe { *RX.0.get() = Some(rx_producer) };

    let rosc = hal::rosc::RingOscillator::new(pac.ROSC).initialize();
    let nonce = nonce(&rosc.free());
    let endpoint: &'static mut McuEndpoint = cortex_m::singleton!(: McuEndpoint = Endpoint::new(
        MachineConfig {
            timer_hz: TIMER_HZ,
            axis_count: 3,
            initial_steps,
        },
        LinkOptions {
            window: LINK_WINDOW,
            retransmit_timeout: TIMER_HZ as u64 / 20,
            nonce,
        },
    ))
    .unwrap();

    // SysTick free-running over its 24 bits at the system clock: the interrupt's cost.
    core.SYST
        .set_clock_source(cortex_m::peripheral::syst::SystClkSource::Core);
    core.SYST.set_reload(0x00FF_FFFF);
    core.SYST.clear_current();
    core.SYST.enable_counter();

    timer()
        .inte()
        .modify(|_, w| w.alarm_0().set_bit().alarm_1().set_bit());
    // SAFETY: priorities set before the interrupts are unmasked; edges preempt everything.
    unsafe {
        core.NVIC.set_priority(pac::Interrupt::TIMER_IRQ_0, 0);
        core.NVIC.set_priority(pac::Interrupt::UART0_IRQ, 0x40);
        core.NVIC.set_priority(pac::Interrupt::TIMER_IRQ_1, 0x80);
        pac::NVIC::unmask(pac::Interrupt::TIMER_IRQ_0);
        pac::NVIC::unmask(pac::Interrupt::TIMER_IRQ_1);
        pac::NVIC::unmask(pac::Interrupt::UART0_IRQ);
    }

    let mut bytes = [0u8; 64];
    let mut frame = [0u8; MAX_WIRE_FRAME];
    let mut screw_output = (0i32, false);
    let mut stopped = false;
    // The motors held: a host owns the MCU (or seed 001's program runs) and no fault.
    let mut energised = false;
    let mut seed_started = false;
    let mut link_on = Transport::Uart;
    let mut uart_out = TxQueue::<UART_TX>::new();
    let mut line_sent: Option<[i32; 3]> = None;
    let mut line_sent_at = 0u64;
    let mut switch_low_since: Option<u64> = None;
    let mut switch_counted = false;
    // The hardware watchdog restarts the chip if the main loop stops passing, which the
    // host-silence check inside it cannot see: the firmware starts again idle (nothing
    // stepping, pin closed, screw stopped) and the host sees a restarted MCU, a fault. A
    // pass takes at most a few ms (main_max_cycles in the firmware tests: at most 156k
    // cycles, 1.25 ms; tests/firmware/run.sh holds it under the 1.75 ms the lead leaves). A
    // panic or a HardFault stops it: they stay halted, every output safe.
    watchdog.start(rp2040_hal::fugit::MicrosDurationU32::millis(100));
    loop {
        let pass_started = cortex_m::peripheral::SYST::get_current();
        let stopped_at_start = stopped;
        let now = timer_now();
        let generate_until = now + LEAD_TICKS;
        usb.poll(&mut [&mut usb_link, &mut usb_lines]);
        for packet in 0.. {
            if packet == USB_PACKETS_PER_PASS {
                MAIN_WORK.store(true, Ordering::Relaxed); // more waiting: another pass at once
                break;
            }
            let n = usb_link.read(&mut bytes).unwrap_or(0);
            if n == 0 {
                break;
            }
            link_on = Transport::Usb;
            bump(&USB_LINK_BYTES_IN, n as u32);
            endpoint.receive(&bytes[..n], now);
        }
        // The start switch (bench rig): pressed (low) for the debounce time, once per press.
        if let Some(pin) = profile::START_SWITCH_PIN {
            if sio().gpio_in().read().bits() & (1 << pin) == 0 {
                let since = *switch_low_since.get_or_insert(now);
                if !switch_counted && now - since >= SWITCH_DEBOUNCE_TICKS {
                    switch_counted = true;
                    if endpoint.start_seed_program(now, SEED_PROGRAM_LEAD_TICKS) {
                        bump(&SEED_PROGRAM_STARTS, 1);
                        seed_started = true;
                    }
                }
            } else {
                switch_low_since = None;
                switch_counted = false;
            }
        }
        // At most one edge per tick: advancing by no more ticks than the queue has free
        // places (less one, kept for the screw) can never overflow it. A full queue holds the
        // generator back (edges would then be late, which `LATE_STEP_OUTPUTS` counts)
        // instead of losing an edge. A chunk ends where the next screw command takes effect,
        // so the screw's output carries that command's own tick: sampled once per pass it
        // went out wherever the pass ended, up to the whole lead late after a long pass.
        loop {
            // What UART0 brought meanwhile first: an emergency stop acts between chunks, not
            // after a whole pass (a pass through a hold's ramp can outlast a control period).
            if take_received(&mut received, endpoint, &mut bytes) {
                link_on = Transport::Uart;
            }
            if endpoint.machine().fault() != FaultCode::None {
                // Faulted, the clock follows time in one step (nothing is generated): a
                // reset after hours faulted then has nothing to catch up chunk by chunk,
                // which kept the MCU deaf for minutes.
                endpoint.advance(generate_until, &mut |_| {});
                break;
            }
            let generated_to = endpoint.machine().clock();
            let free = (to_pins.capacity() - to_pins.len()).saturating_sub(1) as u64;
            if generated_to >= generate_until || free == 0 {
                break;
            }
            let chunk = if endpoint.machine().mode() == Mode::Ramping {
                RAMP_CHUNK_TICKS
            } else {
                GENERATE_CHUNK_TICKS
            };
            let mut until = generate_until
                .min(generated_to + free)
                .min(generated_to + chunk);
            if let Some(ticks) = endpoint.machine().ticks_to_next_screw_command() {
                until = until.min(generated_to.saturating_add(ticks.max(1)));
            }
            endpoint.advance(until, &mut |edge| {
                let writes = outputs.edge(edge);
                let queued = to_pins.enqueue(Output::Step { edge, writes });
                debug_assert!(queued.is_ok(), "one edge per tick at most");
            });
            sample_screw(endpoint.machine(), &mut screw_output, &mut to_pins);
        }
        let machine = endpoint.machine();
        sample_screw(machine, &mut screw_output, &mut to_pins);
        let faulted = machine.fault() != FaultCode::None;
        let owned = machine.host_configured() || seed_started;
        if faulted && !stopped {
            stop_outputs(endpoint, &mut outputs);
            screw_output = (0, false);
            energised = false;
        }
        if !faulted && owned && !energised {
            restart_outputs(&outputs);
            energised = true;
        }
        stopped = faulted;
        // Let the output interrupt arm its alarm for what was just queued.
        pac::NVIC::pend(pac::Interrupt::TIMER_IRQ_0);
        match link_on {
            Transport::Uart => {
                uart_out.flush_uart();
                uart_out.fill(endpoint, now, &mut frame);
                uart_out.flush_uart();
            }
            Transport::Usb => {
                let mut sent = usb_link_out.flush_usb(&mut usb_link);
                usb_link_out.fill(endpoint, now, &mut frame);
                sent += usb_link_out.flush_usb(&mut usb_link);
                bump(&USB_LINK_BYTES_OUT, sent as u32);
            }
        }
        // Seed 001's position lines, while a terminal holds the port open (DTR).
        let position = endpoint.machine().positions();
        if usb_lines.dtr()
            && line_sent != Some(position)
            && now - line_sent_at >= LINES_PERIOD_TICKS
            && usb_lines_out
                .push(cell_firmware_core::seed_program::position_line(position).as_bytes())
        {
            line_sent = Some(position);
            line_sent_at = now;
            bump(&POSITION_LINES, 1);
        }
        usb_lines_out.flush_usb(&mut usb_lines);
        let counters = endpoint.counters();
        BAD_FRAMES.store(
            counters.crc_errors + counters.framing_errors,
            Ordering::Relaxed,
        );
        NAKS_SENT.store(counters.naks_sent, Ordering::Relaxed);
        let spent =
            pass_started.wrapping_sub(cortex_m::peripheral::SYST::get_current()) & 0x00FF_FFFF;
        if !stopped_at_start && !stopped && spent > MAIN_MAX_CYCLES.load(Ordering::Relaxed) {
            MAIN_MAX_CYCLES.store(spent, Ordering::Relaxed);
        }
        let wake = (timer_now() as u32).wrapping_add(LOOP_PERIOD_TICKS);
        timer().alarm1().write(|w| unsafe { w.bits(wake) });
        // An alarm fires only on its exact tick: one armed already past would wake the
        // loop only when the timer comes round again, 71 minutes later.
        if (wake.wrapping_sub(timer_low()) as i32) <= 0 {
            MAIN_WORK.store(true, Ordering::Relaxed);
        }
        watchdog.feed();
        // Asleep until a period or a frame gives work. WFE, not WFI: an interrupt's return
        // sets the event register, so one that sets the flag just after the test ends the
        // next WFE at once instead of leaving the pass to wait for another interrupt (and
        // masking interrupts around a WFI instead would hold the step interrupt back).
        while !MAIN_WORK.load(Ordering::Relaxed) {
            cortex_m::asm::wfe();
        }
        MAIN_WORK.store(false, Ordering::Relaxed);
    }
}

/// A safe state whatever broke: step, direction and coil pins low, drivers disabled, the pin
/// closed and the screw's PWM at 0 (GP13 is the PWM's, so clearing SIO outputs leaves it
/// running).
fn force_safe_outputs() {
    // SAFETY: the watchdog's control register: halted here, the chip stays halted and
    // safe rather than restarting 100 ms later with its drivers enabled again.
    unsafe { &*pac::WATCHDOG::ptr() }
        .ctrl()
        .modify(|_, w| w.enable().clear_bit());
    profile::disable_drivers();
    sio()
        .gpio_out_clr()
        .write(|w| unsafe { w.bits(profile::ALL_OUTPUTS & !profile::ENABLE_MASK) });
    // SAFETY: the screw slice's compare register; nothing else runs any more.
    let pwm = unsafe { &*pac::PWM::ptr() };
    pwm.ch(profile::SCREW_PWM_SLICE)
        .cc()
        .write(|w| unsafe { w.bits(0) });
}

#[panic_handler]
fn panic(_: &core::panic::PanicInfo) -> ! {
    cortex_m::interrupt::disable();
    force_safe_outputs();
    loop {
        cortex_m::asm::wfi();
    }
}

/// A bus fault, a bad instruction: the default handler spins with every output as it was.
#[cortex_m_rt::exception]
unsafe fn HardFault(_frame: &cortex_m_rt::ExceptionFrame) -> ! {
    cortex_m::interrupt::disable();
    force_safe_outputs();
    loop {
        cortex_m::asm::wfi();
    }
}
