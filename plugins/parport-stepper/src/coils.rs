//! Coil excitation sequences of a two-phase bipolar stepper and their mapping to data-register
//! bits. A coil pattern is 4 bits: A+ (bit 0), A- (bit 1), B+ (bit 2), B- (bit 3) — the four
//! H-bridge inputs of one motor.

const A_PLUS: u8 = 0b0001;
const A_MINUS: u8 = 0b0010;
const B_PLUS: u8 = 0b0100;
const B_MINUS: u8 = 0b1000;

/// How the coils of one motor are driven.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Excitation {
    /// Two phases on at all times (the seed's sequence): full torque.
    #[default]
    FullStep,
    /// One phase on at a time ("wave"): less torque, less current.
    Wave,
    /// Alternates one and two phases: twice the steps per turn.
    HalfStep,
}

const FULL: [u8; 4] = [
    A_PLUS | B_PLUS,
    A_MINUS | B_PLUS,
    A_MINUS | B_MINUS,
    A_PLUS | B_MINUS,
];
const WAVE: [u8; 4] = [A_PLUS, B_PLUS, A_MINUS, B_MINUS];
const HALF: [u8; 8] = [
    A_PLUS,
    A_PLUS | B_PLUS,
    B_PLUS,
    A_MINUS | B_PLUS,
    A_MINUS,
    A_MINUS | B_MINUS,
    B_MINUS,
    A_PLUS | B_MINUS,
];

impl Excitation {
    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "full_step" => Some(Excitation::FullStep),
            "wave" => Some(Excitation::Wave),
            "half_step" => Some(Excitation::HalfStep),
            _ => None,
        }
    }

    /// The sequence; stepping forward walks it up, backward walks it down.
    pub fn sequence(self) -> &'static [u8] {
        match self {
            Excitation::FullStep => &FULL,
            Excitation::Wave => &WAVE,
            Excitation::HalfStep => &HALF,
        }
    }

    /// The pattern for motor position `steps`.
    pub fn pattern(self, steps: i64) -> u8 {
        let seq = self.sequence();
        seq[steps.rem_euclid(seq.len() as i64) as usize]
    }

    /// Whether `to` may follow `from` on the coils: the same pattern or one step either way.
    /// Anything else skips a phase (the rotor may jump or stall).
    pub fn is_legal_transition(self, from: u8, to: u8) -> bool {
        let seq = self.sequence();
        let (Some(i), Some(j)) = (
            seq.iter().position(|p| *p == from),
            seq.iter().position(|p| *p == to),
        ) else {
            return false;
        };
        let d = (j + seq.len() - i) % seq.len();
        d == 0 || d == 1 || d == seq.len() - 1
    }
}

/// Where one motor's four coil lines are on the data register, and its sequence.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CoilMap {
    pub excitation: Excitation,
    /// Data-register bit (0..=7) of A+, A-, B+, B-.
    pub bits: [u8; 4],
}

impl CoilMap {
    /// Data-register bits driven by this motor.
    pub fn mask(&self) -> u8 {
        self.bits.iter().fold(0, |m, b| m | (1 << b))
    }

    /// The register bits for motor position `steps` (energised).
    pub fn register_bits(&self, steps: i64) -> u8 {
        self.spread(self.excitation.pattern(steps))
    }

    /// Moves a 4-bit coil pattern onto this motor's register bits.
    pub fn spread(&self, pattern: u8) -> u8 {
        let mut out = 0;
        for (i, bit) in self.bits.iter().enumerate() {
            if pattern & (1 << i) != 0 {
                out |= 1 << bit;
            }
        }
        out
    }

    /// The 4-bit coil pattern this motor sees in a data-register value.
    pub fn gather(&self, register: u8) -> u8 {
        let mut out = 0;
        for (i, bit) in self.bits.iter().enumerate() {
            if register & (1 << bit) != 0 {
                out |= 1 << i;
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sequences_step_one_phase_at_a_time() {
        for e in [Excitation::FullStep, Excitation::Wave, Excitation::HalfStep] {
            let seq = e.sequence();
            for i in 0..seq.len() {
                let next = seq[(i + 1) % seq.len()];
                assert!(e.is_legal_transition(seq[i], next));
                assert!(e.is_legal_transition(next, seq[i]));
                // Never both ends of one H-bridge at once.
                assert_ne!(seq[i] & 0b0011, 0b0011);
                assert_ne!(seq[i] & 0b1100, 0b1100);
            }
        }
        // Two positions apart is a skipped phase.
        assert!(!Excitation::FullStep.is_legal_transition(FULL[0], FULL[2]));
        assert!(!Excitation::HalfStep.is_legal_transition(HALF[0], HALF[2]));
        assert_eq!(Excitation::FullStep.pattern(-1), FULL[3]);
    }

    #[test]
    fn register_bits_follow_the_pin_map() {
        let y = CoilMap {
            excitation: Excitation::FullStep,
            bits: [4, 5, 6, 7],
        };
        assert_eq!(y.mask(), 0xF0);
        assert_eq!(y.register_bits(0), (A_PLUS | B_PLUS) << 4);
        assert_eq!(y.gather(y.register_bits(3)), FULL[3]);
    }
}
