//! Which pin does what: the cell (step/dir drivers) or seed 001's bench rig (`--features
//! bench-rig`: three 28BYJ-48 motors on ULN2003 boards). Both keep UART0 on GP16/GP17 and the
//! screw on GP12 (pin) and GP13 (speed, PWM slice 6 channel B).
//!
//! | GPIO   | cell                          | bench rig (seed 001)          |
//! |--------|-------------------------------|-------------------------------|
//! | 0, 1   | bed STEP, DIR                 | X coils IN1, IN2              |
//! | 2, 3   | —                             | X coils IN3, IN4              |
//! | 4, 5   | arm STEP, DIR                 | Y coils IN1, IN2              |
//! | 6, 7   | —                             | Y coils IN3, IN4              |
//! | 8, 9   | z STEP, DIR                   | Z coils IN1, IN2              |
//! | 10, 11 | —                             | Z coils IN3, IN4              |
//! | 12     | screw pin (high: open)        | screw pin                     |
//! | 13     | screw speed, PWM 12.5 kHz     | screw speed                   |
//! | 14     | drivers' ENABLE (low: on)     | —                             |
//! | 15     | —                             | start switch (to ground)      |
//! | 16, 17 | UART0 TX, RX                  | UART0 TX, RX                  |

use cell_firmware_core::outputs::OutputStage;
use rp2040_hal::pac;

/// The screw pin.
pub const SCREW_PIN: u8 = 12;
/// The PWM slice of GP13 (channel B).
pub const SCREW_PWM_SLICE: usize = 6;
/// Screw speed at full PWM duty: the URDF's limit of the screw joint (300 rpm).
pub const SCREW_FULL_SCALE_MILLIRPM: i32 = 300_000;

#[cfg(not(feature = "bench-rig"))]
mod pins {
    use super::OutputStage;
    pub const STAGES: [OutputStage; 3] = [
        OutputStage::StepDir {
            step_pin: 0,
            dir_pin: 1,
            dir_inverted: false,
        },
        OutputStage::StepDir {
            step_pin: 4,
            dir_pin: 5,
            dir_inverted: false,
        },
        OutputStage::StepDir {
            step_pin: 8,
            dir_pin: 9,
            dir_inverted: false,
        },
    ];
    /// The step/dir drivers' shared enable, active low.
    pub const ENABLE_PIN: Option<u8> = Some(14);
    pub const START_SWITCH_PIN: Option<u8> = None;
}

#[cfg(feature = "bench-rig")]
mod pins {
    use super::OutputStage;
    pub const STAGES: [OutputStage; 3] = [
        OutputStage::FourCoil { pins: [0, 1, 2, 3] },
        OutputStage::FourCoil { pins: [4, 5, 6, 7] },
        OutputStage::FourCoil {
            pins: [8, 9, 10, 11],
        },
    ];
    pub const ENABLE_PIN: Option<u8> = None;
    /// Seed 001's start switch, to ground (input with pull-up).
    pub const START_SWITCH_PIN: Option<u8> = Some(15);
}

pub use pins::{STAGES, START_SWITCH_PIN};

/// Every pin the firmware drives (the panic handler's safe state clears them all but the
/// enable pin, which it sets: cleared, even for an instant, it would enable the drivers).
pub const ALL_OUTPUTS: u32 = 0x0000_3FFF;

/// The drivers' enable pin as a mask (0 without one).
pub const ENABLE_MASK: u32 = match pins::ENABLE_PIN {
    Some(pin) => 1 << pin,
    None => 0,
};

fn sio() -> &'static pac::sio::RegisterBlock {
    // SAFETY: single-write set/clear registers.
    unsafe { &*pac::SIO::ptr() }
}

/// The stages' pins, the screw pin and the enable pin as SIO outputs at `levels`, the
/// drivers disabled: the main loop enables them once a host has configured the MCU, so a
/// board waiting for its host holds no current in the motors.
pub fn configure_pins(stage_mask: u32, levels: u32) {
    // SAFETY: called once from `main` after the HAL has taken IO_BANK0/PADS_BANK0 out of
    // reset, for pins the HAL was not asked to drive.
    let io = unsafe { &*pac::IO_BANK0::ptr() };
    let pads = unsafe { &*pac::PADS_BANK0::ptr() };
    let mask = stage_mask | (1 << SCREW_PIN) | ENABLE_MASK;
    sio()
        .gpio_out_clr()
        .write(|w| unsafe { w.bits(mask & !ENABLE_MASK) });
    sio()
        .gpio_out_set()
        .write(|w| unsafe { w.bits(levels | ENABLE_MASK) });
    for pin in (0..30).filter(|p| mask & (1 << p) != 0) {
        pads.gpio(pin)
            .modify(|_, w| w.od().clear_bit().ie().set_bit());
        io.gpio(pin).gpio_ctrl().write(|w| w.funcsel().sio());
    }
    sio().gpio_oe_set().write(|w| unsafe { w.bits(mask) });
    #[cfg(feature = "bench-rig")]
    {
        // The start switch: input with pull-up (pressed reads low).
        pads.gpio(15)
            .modify(|_, w| w.ie().set_bit().pue().set_bit().pde().clear_bit());
        io.gpio(15).gpio_ctrl().write(|w| w.funcsel().sio());
    }
}

pub fn enable_drivers() {
    if let Some(pin) = pins::ENABLE_PIN {
        sio().gpio_out_clr().write(|w| unsafe { w.bits(1 << pin) });
    }
}

/// Drivers off (step/dir: enable released; coils are released by the caller).
pub fn disable_drivers() {
    if let Some(pin) = pins::ENABLE_PIN {
        sio().gpio_out_set().write(|w| unsafe { w.bits(1 << pin) });
    }
}
