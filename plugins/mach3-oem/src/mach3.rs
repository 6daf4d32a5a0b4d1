//! The one interface to Mach3: the `IMyScriptObject` methods this adapter uses, as a Rust trait.
//! Implemented by the Windows COM client (`com.rs`) and by the simulator (`sim.rs`); the agent
//! only ever talks to `dyn Mach3`, so everything above it is tested on Linux.

use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

/// Why a Mach3 call failed. `kind` travels over the agent protocol.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error, Serialize, Deserialize)]
#[error("{message}")]
pub struct Mach3Error {
    pub kind: ErrorKind,
    pub message: String,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ErrorKind {
    /// Mach3 is not running in this desktop session (`MK_E_UNAVAILABLE`).
    NotRunning,
    /// The call did not return within the agent's per-call timeout.
    Timeout,
    /// Any other COM failure (Mach3 closed mid-call, dispatch error, ...).
    Com,
    /// The request itself is wrong (bad program, bad file name, ...).
    Invalid,
    /// The agent could not read or write a file.
    Io,
    /// Handshake refused: wrong secret.
    Auth,
    /// Handshake refused: protocol version, or a malformed frame.
    Protocol,
}

impl Mach3Error {
    pub fn new(kind: ErrorKind, message: impl Into<String>) -> Self {
        Mach3Error {
            kind,
            message: message.into(),
        }
    }
    pub fn invalid(message: impl Into<String>) -> Self {
        Self::new(ErrorKind::Invalid, message)
    }
}

pub type Mach3Result<T> = Result<T, Mach3Error>;

/// The `IMyScriptObject` methods Fresa uses (DISPIDs in `com.rs`). Codes are Mach3's `short`s.
/// Implementations live on one thread (COM's single-threaded apartment), hence `&mut self`
/// and no `Send` bound.
pub trait Mach3 {
    /// `DoOEMButton(short)`.
    fn do_oem_button(&mut self, code: i16) -> Mach3Result<()>;
    /// `GetOEMDRO(short) -> double`.
    fn get_oem_dro(&mut self, code: i16) -> Mach3Result<f64>;
    /// `SetOEMDRO(short, double)`.
    fn set_oem_dro(&mut self, code: i16, value: f64) -> Mach3Result<()>;
    /// `GetOEMLed(short) -> BOOL`.
    fn get_oem_led(&mut self, code: i16) -> Mach3Result<bool>;
    /// `Code(BSTR)`: one MDI line.
    fn code(&mut self, line: &str) -> Mach3Result<()>;
    /// `LoadFile(BSTR)`: a path as Mach3 (on this PC) sees it.
    fn load_file(&mut self, path: &str) -> Mach3Result<()>;
    /// `JogOn(short axis, short dir)`: runs until `JogOff`. Axis 0..5 = X..C, dir 0 = +, 1 = -.
    fn jog_on(&mut self, axis: i16, direction: i16) -> Mach3Result<()>;
    /// `JogOff(short axis)`.
    fn jog_off(&mut self, axis: i16) -> Mach3Result<()>;
    /// `IsMoving()`.
    fn is_moving(&mut self) -> Mach3Result<bool>;
    /// `IsEstop()`.
    fn is_estop(&mut self) -> Mach3Result<bool>;
    /// `GetVar(n) -> double`: G-code parameter `#n` (G31 leaves its trip in #2000-#2005).
    /// Not in the project's DISPID list: the COM side looks it up by name.
    fn get_var(&mut self, var: i16) -> Mach3Result<f64>;
}

/// One Mach3 method call as it travels in an agent request (`{"op":"get_oem_dro","code":800}`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "op", rename_all = "snake_case", deny_unknown_fields)]
pub enum Call {
    DoOemButton {
        code: i16,
    },
    GetOemDro {
        code: i16,
    },
    SetOemDro {
        code: i16,
        value: f64,
    },
    GetOemLed {
        code: i16,
    },
    Code {
        line: String,
    },
    LoadFile {
        path: String,
    },
    JogOn {
        axis: i16,
        direction: i16,
    },
    JogOff {
        axis: i16,
    },
    IsMoving,
    IsEstop,
    /// Protocol feature `get_var` (see [`crate::protocol::FEATURES`]).
    GetVar {
        var: i16,
    },
    /// Not a Mach3 method: the agent stores a program under its program directory, in chunks
    /// (`first` truncates, `last` finishes and answers the full path to give `load_file`).
    WriteProgram {
        name: String,
        data: String,
        first: bool,
        last: bool,
    },
}

impl Call {
    /// Runs a Mach3 method call; `WriteProgram` is the agent's and is refused here.
    pub fn apply(&self, m: &mut dyn Mach3) -> Mach3Result<Value> {
        Ok(match self {
            Call::DoOemButton { code } => {
                m.do_oem_button(*code)?;
                Value::Null
            }
            Call::GetOemDro { code } => json!(m.get_oem_dro(*code)?),
            Call::SetOemDro { code, value } => {
                if !value.is_finite() {
                    return Err(Mach3Error::invalid(format!(
                        "SetOEMDRO({code}): value must be a finite number"
                    )));
                }
                m.set_oem_dro(*code, *value)?;
                Value::Null
            }
            Call::GetOemLed { code } => json!(m.get_oem_led(*code)?),
            Call::Code { line } => {
                if line.contains(['\n', '\r']) {
                    return Err(Mach3Error::invalid(
                        "Code(): one MDI line, without newlines",
                    ));
                }
                m.code(line)?;
                Value::Null
            }
            Call::LoadFile { path } => {
                m.load_file(path)?;
                Value::Null
            }
            Call::JogOn { axis, direction } => {
                check_axis(*axis)?;
                m.jog_on(*axis, *direction)?;
                Value::Null
            }
            Call::JogOff { axis } => {
                check_axis(*axis)?;
                m.jog_off(*axis)?;
                Value::Null
            }
            Call::IsMoving => json!(m.is_moving()?),
            Call::IsEstop => json!(m.is_estop()?),
            Call::GetVar { var } => {
                if *var < 0 {
                    return Err(Mach3Error::invalid(format!(
                        "GetVar({var}): G-code parameters are numbered from 0"
                    )));
                }
                json!(m.get_var(*var)?)
            }
            Call::WriteProgram { .. } => {
                return Err(Mach3Error::invalid(
                    "write_program is handled by the agent, not Mach3",
                ))
            }
        })
    }
}

fn check_axis(axis: i16) -> Mach3Result<()> {
    if (0..6).contains(&axis) {
        Ok(())
    } else {
        Err(Mach3Error::invalid(format!(
            "axis {axis} is not a Mach3 axis (0..5 = X..C)"
        )))
    }
}
