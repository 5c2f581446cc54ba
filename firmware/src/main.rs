//! The polar cell's RP2040 firmware: `cell_firmware_core` on a Raspberry Pi Pico.
//!
//! Everything the MCU decides is in `cell_firmware_core` (host-tested, and run by the
//! `mcu_emulator`); this crate only connects it to the chip:
//!
//! * **UART0** (GP16 TX, GP17 RX, 921,600 baud, 8N1) carries the wire protocol
//!   (`nodes/cell_protocol/PROTOCOL.md`). Received bytes are moved to a ring by the UART's
//!   interrupt, so a frame being decoded never overruns the 32-byte FIFO.
//! * **Step timing** comes from the 1 MHz hardware timer, which is the MCU clock of the
//!   protocol plus a fixed lead: the main loop generates edges [`LEAD_TICKS`] ahead into an
//!   output queue, and the timer's ALARM0 interrupt (highest priority) writes each edge to
//!   the pins when the timer reaches it. The clock the firmware reports is the generator's,
//!   so the host schedules in it and the pins follow exactly `LEAD_TICKS` later; what the
//!   queue still holds at an emergency stop is dropped and taken back from the positions.
//! * **Outputs** per axis from the build profile (`profile.rs`): step/dir drivers with a
//!   shared enable for the cell, or four coil inputs per 28BYJ-48 for seed 001's bench rig;
//!   the screw's pin on GP12 and its speed as PWM duty on GP13.
//!
//! Faults stop the outputs at once (edges dropped, drivers disabled or coils released, pin
//! closed, screw 0) and are latched by the core until the host resets it.
//!
//! No ROM calls: the clocks, UART and timer are set up through `rp2040-hal`, whose start-up
//! does not call the boot ROM, so the same image runs on a Pico and in `rp2040js` (which
//! has no boot ROM; `tests/firmware/`).

#![no_std]
#![no_main]

mod profile;

use core::cell::RefCell;
use core::sync::atomic::{AtomicU32, Ordering};

use cell_firmware_core::outputs::Outputs;
use cell_firmware_core::{Endpoint, MachineConfig, StepEdge};
use cell_protocol::message::FaultCode;
use cell_protocol::{LinkOptions, MAX_WIRE_FRAME};
use critical_section::Mutex;
use heapless::spsc::{Consumer, Producer, Queue};
use rp2040_hal as hal;
use rp2040_hal::fugit::RateExtU32;
use rp2040_hal::pac::{self, interrupt};

/// The second-stage bootloader for the Pico's W25Q080-compatible flash.
#[link_section = ".boot2"]
#[used]
pub static BOOT2: [u8; 256] = rp2040_boot2::BOOT_LOADER_W25Q080;

/// The Pico's crystal.
const XTAL_HZ: u32 = 12_000_000;
/// The MCU clock: the hardware timer's 1 µs tick.
const TIMER_HZ: u32 = 1_000_000;
/// How far ahead of the pins the edges are generated (ticks): longer than the main loop's
/// worst pass (a frame decoded and a segment queued, some 100 µs at 125 MHz), short enough
/// that a stop drops little.
pub const LEAD_TICKS: u64 = 2_000;
/// The main loop's wake-up period when no byte arrives (ticks).
const LOOP_PERIOD_TICKS: u32 = 250;
/// Step pulse width (ticks): step/dir drivers need 1–2 µs high; it ends 2–3 µs after the edge.
const PULSE_TICKS: u64 = 3;
/// Direction set-up before a step that changes it, in cycles: 200 ns at 125 MHz (A4988's
/// minimum; a DRV8825 wants 650 ns, a TMC2209 20 ns).
const DIR_SETUP_CYCLES: u32 = 25;
/// PWM top of the screw's speed output: 125 MHz / 10,000 = 12.5 kHz.
const PWM_TOP: u16 = 9_999;

const LINK_WINDOW: usize = 16;
const SEGMENT_QUEUE: usize = 256;
const SCREW_QUEUE: usize = 512;
const OUTPUT_QUEUE: usize = 512;
const RX_RING: usize = 2048;

type McuEndpoint = Endpoint<LINK_WINDOW, SEGMENT_QUEUE, SCREW_QUEUE>;

/// What the ALARM0 interrupt writes to the pins, at `clock` (MCU clock; pins at clock − lead).
#[derive(Clone, Copy, Debug)]
enum Output {
    Step(StepEdge),
    Screw {
        clock: u64,
        millirpm: i32,
        pin_open: bool,
    },
}

impl Output {
    fn clock(&self) -> u64 {
        match *self {
            Output::Step(edge) => edge.clock,
            Output::Screw { clock, .. } => clock,
        }
    }
}

/// The output stage, owned by the ALARM0 interrupt; the main loop takes it only to stop.
struct OutputStage {
    queue: Consumer<'static, Output>,
    outputs: Outputs,
    /// Step pins high and the tick from which they go low.
    pulse: Option<(u32, u64)>,
}

static OUTPUT_STAGE: Mutex<RefCell<Option<OutputStage>>> = Mutex::new(RefCell::new(None));
static RX: Mutex<RefCell<Option<Producer<'static, u8>>>> = Mutex::new(RefCell::new(None));

/// Worst cycles spent in one ALARM0 interrupt (SysTick counts them), read by the
/// firmware-in-the-loop harness from RAM.
#[no_mangle]
pub static ISR_MAX_CYCLES: AtomicU32 = AtomicU32::new(0);
/// Edges written to the pins.
#[no_mangle]
pub static EDGES_OUTPUT: AtomicU32 = AtomicU32::new(0);
/// Bytes lost because the receive ring was full.
#[no_mangle]
pub static RX_OVERRUNS: AtomicU32 = AtomicU32::new(0);
/// Edges the generator made that found the output queue full (a fault follows).
#[no_mangle]
pub static OUTPUT_OVERFLOWS: AtomicU32 = AtomicU32::new(0);

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

fn set_screw_outputs(millirpm: i32, pin_open: bool) {
    let duty = (millirpm.clamp(0, profile::SCREW_FULL_SCALE_MILLIRPM) as u64 * (PWM_TOP as u64 + 1)
        / profile::SCREW_FULL_SCALE_MILLIRPM as u64) as u16;
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

/// Write every output that is due, end step pulses whose width has passed, then arm ALARM0
/// for whichever comes next. Pulses end by the alarm too, not by waiting in here, so an edge
/// of another axis one tick later is still written on its tick.
#[interrupt]
fn TIMER_IRQ_0() {
    let entered = cortex_m::peripheral::SYST::get_current();
    timer().intr().write(|w| w.alarm_0().clear_bit_by_one());
    critical_section::with(|cs| {
        let mut stage = OUTPUT_STAGE.borrow_ref_mut(cs);
        let Some(stage) = stage.as_mut() else { return };
        loop {
            let now = timer_now();
            if let Some((mask, high_until)) = stage.pulse {
                if now >= high_until {
                    sio().gpio_out_clr().write(|r| unsafe { r.bits(mask) });
                    stage.pulse = None;
                }
            }
            let next_due = stage
                .queue
                .peek()
                .map(|next| next.clock().saturating_sub(LEAD_TICKS));
            match next_due {
                Some(due) if due <= now => {}
                _ => {
                    let wake = match (next_due, stage.pulse) {
                        (Some(due), Some((_, end))) => due.min(end),
                        (Some(due), None) => due,
                        (None, Some((_, end))) => end,
                        (None, None) => break,
                    };
                    timer().alarm0().write(|w| unsafe { w.bits(wake as u32) });
                    // Armed for a time still ahead: done. Passed meanwhile: disarm and go
                    // round again (an alarm only fires on an exact match).
                    if wake > timer_now() {
                        break;
                    }
                    timer().armed().write(|w| unsafe { w.bits(1) });
                    continue;
                }
            }
            let Some(next) = stage.queue.dequeue() else {
                break;
            };
            match next {
                Output::Step(edge) => {
                    let w = stage.outputs.edge(edge);
                    if w.dir_set | w.dir_clear != 0 {
                        sio().gpio_out_set().write(|r| unsafe { r.bits(w.dir_set) });
                        sio()
                            .gpio_out_clr()
                            .write(|r| unsafe { r.bits(w.dir_clear) });
                        cortex_m::asm::delay(DIR_SETUP_CYCLES);
                    }
                    sio().gpio_out_xor().write(|r| unsafe { r.bits(w.toggle) });
                    if w.pulse_end != 0 {
                        let mask = stage.pulse.map_or(0, |(m, _)| m) | w.pulse_end;
                        stage.pulse = Some((mask, now + PULSE_TICKS));
                    }
                    EDGES_OUTPUT.store(EDGES_OUTPUT.load(Ordering::Relaxed) + 1, Ordering::Relaxed);
                }
                Output::Screw {
                    millirpm, pin_open, ..
                } => set_screw_outputs(millirpm, pin_open),
            }
        }
    });
    // SysTick counts down from its reload value (24 bits, wraps every 134 ms at 125 MHz).
    let left = cortex_m::peripheral::SYST::get_current();
    let spent = entered.wrapping_sub(left) & 0x00FF_FFFF;
    if spent > ISR_MAX_CYCLES.load(Ordering::Relaxed) {
        ISR_MAX_CYCLES.store(spent, Ordering::Relaxed);
    }
}

/// The main loop's tick: nothing to do but wake it.
#[interrupt]
fn TIMER_IRQ_1() {
    timer().intr().write(|w| w.alarm_1().clear_bit_by_one());
}

/// Move received bytes from the UART's FIFO to the ring.
#[interrupt]
fn UART0_IRQ() {
    // SAFETY: the data and flag registers; the main loop only transmits.
    let uart = unsafe { &*pac::UART0::ptr() };
    critical_section::with(|cs| {
        let mut rx = RX.borrow_ref_mut(cs);
        let Some(rx) = rx.as_mut() else { return };
        while uart.uartfr().read().rxfe().bit_is_clear() {
            let byte = uart.uartdr().read().data().bits();
            if rx.enqueue(byte).is_err() {
                RX_OVERRUNS.store(RX_OVERRUNS.load(Ordering::Relaxed) + 1, Ordering::Relaxed);
            }
        }
    });
}

fn uart_write(bytes: &[u8]) {
    // SAFETY: the data and flag registers; the interrupt only receives.
    let uart = unsafe { &*pac::UART0::ptr() };
    for &byte in bytes {
        while uart.uartfr().read().txff().bit_is_set() {}
        uart.uartdr().write(|w| unsafe { w.data().bits(byte) });
    }
}

/// A nonce for the link session: the ring oscillator's jitter, one bit at a time.
fn nonce(rosc: &pac::ROSC) -> u32 {
    (0..32).fold(0, |n, _| {
        (n << 1) | rosc.randombit().read().randombit().bit() as u32
    })
}

/// Stop every output now: drop the queued edges (and take them back from the positions),
/// release the motors, close the pin, stop the screw.
fn stop_outputs(endpoint: &mut McuEndpoint) {
    critical_section::with(|cs| {
        let mut stage = OUTPUT_STAGE.borrow_ref_mut(cs);
        if let Some(stage) = stage.as_mut() {
            let queue = &mut stage.queue;
            endpoint.discard_edges(core::iter::from_fn(|| loop {
                match queue.dequeue()? {
                    Output::Step(edge) => return Some(edge),
                    Output::Screw { .. } => continue,
                }
            }));
            let step_pins = stage.pulse.take().map_or(0, |(mask, _)| mask);
            sio()
                .gpio_out_clr()
                .write(|w| unsafe { w.bits(stage.outputs.coil_mask() | step_pins) });
        }
        timer().armed().write(|w| unsafe { w.bits(1) });
    });
    profile::disable_drivers();
    set_screw_outputs(0, false);
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
    let outputs = Outputs::new(profile::STAGES, initial_steps);
    profile::configure_pins(outputs.mask(), outputs.initial_levels());
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

    let outputs_queue = cortex_m::singleton!(: Queue<Output, OUTPUT_QUEUE> = Queue::new()).unwrap();
    let (mut to_pins, from_generator) = outputs_queue.split();
    let rx_ring = cortex_m::singleton!(: Queue<u8, RX_RING> = Queue::new()).unwrap();
    let (rx_producer, mut received) = rx_ring.split();
    critical_section::with(|cs| {
        OUTPUT_STAGE.borrow_ref_mut(cs).replace(OutputStage {
            queue: from_generator,
            outputs,
            pulse: None,
        });
        RX.borrow_ref_mut(cs).replace(rx_producer);
    });

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
    loop {
        let now = timer_now() + LEAD_TICKS;
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
                break;
            }
            endpoint.receive(&bytes[..n], now);
        }
        let mut overflow = false;
        endpoint.advance(now, &mut |edge| {
            if to_pins.enqueue(Output::Step(edge)).is_err() {
                overflow = true;
            }
        });
        if overflow {
            OUTPUT_OVERFLOWS.store(
                OUTPUT_OVERFLOWS.load(Ordering::Relaxed) + 1,
                Ordering::Relaxed,
            );
        }
        let machine = endpoint.machine();
        let screw = (machine.screw_millirpm(), machine.pin_open());
        if screw != screw_output && !to_pins.ready() {
            // Queue full: tried again next pass.
        } else if screw != screw_output {
            let _ = to_pins.enqueue(Output::Screw {
                clock: now,
                millirpm: screw.0,
                pin_open: screw.1,
            });
            screw_output = screw;
        }
        let faulted = machine.fault() != FaultCode::None;
        if faulted && !stopped {
            stop_outputs(endpoint);
            screw_output = (0, false);
        } else if !faulted && stopped {
            profile::enable_drivers();
        }
        stopped = faulted;
        // Let the output interrupt arm its alarm for what was just queued.
        pac::NVIC::pend(pac::Interrupt::TIMER_IRQ_0);
        while let Some(len) = endpoint.poll_transmit(now, &mut frame) {
            uart_write(&frame[..len]);
        }
        let wake = timer_now() as u32 + LOOP_PERIOD_TICKS;
        timer().alarm1().write(|w| unsafe { w.bits(wake) });
        cortex_m::asm::wfi();
    }
}

#[panic_handler]
fn panic(_: &core::panic::PanicInfo) -> ! {
    cortex_m::interrupt::disable();
    // A safe state whatever broke: motors released, pin closed, screw stopped.
    sio()
        .gpio_out_clr()
        .write(|w| unsafe { w.bits(profile::ALL_OUTPUTS) });
    profile::disable_drivers();
    loop {
        cortex_m::asm::wfi();
    }
}
