//! `mpg-pendant`: the transport for ESP32 MPG handwheel pendants that speak the 53-character
//! protocol (see README.md). One plugin instance per pendant: it connects (the pendant is the
//! TCP server), keeps the link alive, decodes what the operator does into [`PendantEvent`]s for
//! the core, and answers the pendant's position/progress polls from a status cache the core pushes.

pub mod codec;

pub use codec::{Decoded, Decoder, Dialect, Frame, Info, FRAME_LEN};
