//! The real Mach3, through COM (Windows only). Lives on the agent's Mach3 thread, which it
//! makes a single-threaded apartment; every call is made there (the agent queues them and
//! gives up waiting after its timeout).
//!
//! Attaches to the RUNNING Mach3 only (`GetActiveObject` by CLSID, which also works from a
//! 64-bit agent when the ProgID is registered only in the 32-bit view), never creates one:
//! that could start a second Mach3 without the machine's profile. When Mach3 goes away the
//! next call fails as "not running" and a later one attaches again (at most once a second).

use crate::mach3::{ErrorKind, Mach3, Mach3Error, Mach3Result};
use std::collections::HashMap;
use std::time::{Duration, Instant};
use windows::core::{Interface, BSTR, GUID, HRESULT, PCWSTR};
use windows::Win32::System::Com::{
    CoInitializeEx, IDispatch, COINIT_APARTMENTTHREADED, DISPATCH_METHOD, DISPPARAMS,
};
use windows::Win32::System::Ole::GetActiveObject;
use windows::Win32::System::Variant::VARIANT;

/// `Mach4.Document` (the historical name of Mach3's document object).
const CLSID_MACH4_DOCUMENT: GUID = GUID::from_u128(0xCA7992B2_2653_4342_8061_D7D385C07809);
const LOCALE_USER_DEFAULT: u32 = 0x0400;
const ATTACH_RETRY: Duration = Duration::from_secs(1);

/// HRESULTs that mean "Mach3 is not (or no longer) running".
const GONE: [u32; 4] = [
    0x800401E3, // MK_E_UNAVAILABLE: not in the running object table
    0x80010108, // RPC_E_DISCONNECTED
    0x800706BA, // RPC_S_SERVER_UNAVAILABLE
    0x800401FD, // CO_E_OBJNOTCONNECTED
];

fn error(context: &str, e: &windows::core::Error) -> Mach3Error {
    let code: HRESULT = e.code();
    let kind = if GONE.contains(&(code.0 as u32)) {
        ErrorKind::NotRunning
    } else {
        ErrorKind::Com
    };
    Mach3Error::new(kind, format!("{context}: {e} (0x{:08X})", code.0 as u32))
}

/// `IMyScriptObject` of the running Mach3.
pub struct ComMach3 {
    script: Option<IDispatch>,
    dispids: HashMap<&'static str, i32>,
    next_attach: Instant,
    last_error: Mach3Error,
}

impl Default for ComMach3 {
    fn default() -> Self {
        Self::new()
    }
}

impl ComMach3 {
    /// Must be called on the thread that makes every later call.
    pub fn new() -> Self {
        // SAFETY: initialises COM for this thread only; the agent's Mach3 thread lives as long
        // as the process, so there is no matching CoUninitialize.
        let hr = unsafe { CoInitializeEx(None, COINIT_APARTMENTTHREADED) };
        if hr.is_err() {
            eprintln!(
                "fresa-mach3-agent: CoInitializeEx failed: 0x{:08X}",
                hr.0 as u32
            );
        }
        ComMach3 {
            script: None,
            dispids: HashMap::new(),
            next_attach: Instant::now(),
            last_error: Mach3Error::new(ErrorKind::NotRunning, "not attached yet"),
        }
    }

    fn attach() -> Mach3Result<IDispatch> {
        let mut unknown = None;
        // SAFETY: valid pointers to a GUID and an out-parameter that lives across the call.
        unsafe { GetActiveObject(&CLSID_MACH4_DOCUMENT, None, &mut unknown) }
            .map_err(|e| error("Mach3 (Mach4.Document) is not running in this session", &e))?;
        let unknown = unknown.ok_or_else(|| {
            Mach3Error::new(ErrorKind::NotRunning, "GetActiveObject returned nothing")
        })?;
        let document: IDispatch = unknown
            .cast()
            .map_err(|e| error("Mach4.Document has no IDispatch", &e))?;
        let id = dispid(&document, "GetScriptDispatch")?;
        let v = invoke(&document, id, Vec::new())?;
        IDispatch::try_from(&v).map_err(|e| error("GetScriptDispatch", &e))
    }

    fn script(&mut self) -> Mach3Result<IDispatch> {
        if let Some(s) = &self.script {
            return Ok(s.clone());
        }
        if Instant::now() < self.next_attach {
            return Err(self.last_error.clone());
        }
        match Self::attach() {
            Ok(s) => {
                self.dispids.clear();
                self.script = Some(s.clone());
                Ok(s)
            }
            Err(e) => {
                self.next_attach = Instant::now() + ATTACH_RETRY;
                self.last_error = e.clone();
                Err(e)
            }
        }
    }

    /// Calls a method by name (DISPID looked up once per attach; `fallback` is the documented
    /// DISPID should the lookup fail).
    fn call(
        &mut self,
        name: &'static str,
        fallback: i32,
        args: Vec<VARIANT>,
    ) -> Mach3Result<VARIANT> {
        let script = self.script()?;
        let id = match self.dispids.get(name) {
            Some(id) => *id,
            None => {
                let id = dispid(&script, name).unwrap_or(fallback);
                self.dispids.insert(name, id);
                id
            }
        };
        invoke(&script, id, args).map_err(|e| {
            if e.kind == ErrorKind::NotRunning {
                self.script = None; // Mach3 went away: attach again next time
            }
            Mach3Error::new(e.kind, format!("{name}: {}", e.message))
        })
    }
}

fn dispid(d: &IDispatch, name: &str) -> Mach3Result<i32> {
    let wide: Vec<u16> = name.encode_utf16().chain(Some(0)).collect();
    let names = [PCWSTR(wide.as_ptr())];
    let mut id = 0i32;
    // SAFETY: one NUL-terminated name that outlives the call, one out DISPID.
    unsafe {
        d.GetIDsOfNames(
            &GUID::zeroed(),
            names.as_ptr(),
            1,
            LOCALE_USER_DEFAULT,
            &mut id,
        )
    }
    .map_err(|e| error(&format!("no method {name}"), &e))?;
    Ok(id)
}

fn invoke(d: &IDispatch, id: i32, mut args: Vec<VARIANT>) -> Mach3Result<VARIANT> {
    args.reverse(); // IDispatch::Invoke takes the last argument first
    let params = DISPPARAMS {
        rgvarg: args.as_mut_ptr(),
        rgdispidNamedArgs: std::ptr::null_mut(),
        cArgs: args.len() as u32,
        cNamedArgs: 0,
    };
    let mut result = VARIANT::default();
    // SAFETY: `params` points into `args`, which outlives the call; `result` is an out VARIANT.
    unsafe {
        d.Invoke(
            id,
            &GUID::zeroed(),
            LOCALE_USER_DEFAULT,
            DISPATCH_METHOD,
            &params,
            Some(&mut result),
            None,
            None,
        )
    }
    .map_err(|e| error("call failed", &e))?;
    Ok(result)
}

fn to_f64(v: &VARIANT) -> Mach3Result<f64> {
    f64::try_from(v).map_err(|e| error("not a number", &e))
}

fn to_bool(v: &VARIANT) -> Mach3Result<bool> {
    bool::try_from(v).map_err(|e| error("not a boolean", &e))
}

impl Mach3 for ComMach3 {
    fn do_oem_button(&mut self, code: i16) -> Mach3Result<()> {
        self.call("DoOEMButton", 0x28, vec![code.into()]).map(drop)
    }
    fn get_oem_dro(&mut self, code: i16) -> Mach3Result<f64> {
        to_f64(&self.call("GetOEMDRO", 0x2d, vec![code.into()])?)
    }
    fn set_oem_dro(&mut self, code: i16, value: f64) -> Mach3Result<()> {
        self.call("SetOEMDRO", 0x30, vec![code.into(), value.into()])
            .map(drop)
    }
    fn get_oem_led(&mut self, code: i16) -> Mach3Result<bool> {
        to_bool(&self.call("GetOEMLed", 0x2c, vec![code.into()])?)
    }
    fn code(&mut self, line: &str) -> Mach3Result<()> {
        self.call("Code", 0x1c, vec![BSTR::from(line).into()])
            .map(drop)
    }
    fn load_file(&mut self, path: &str) -> Mach3Result<()> {
        self.call("LoadFile", 0x88, vec![BSTR::from(path).into()])
            .map(drop)
    }
    fn jog_on(&mut self, axis: i16, direction: i16) -> Mach3Result<()> {
        self.call("JogOn", 0x8b, vec![axis.into(), direction.into()])
            .map(drop)
    }
    fn jog_off(&mut self, axis: i16) -> Mach3Result<()> {
        self.call("JogOff", 0x8c, vec![axis.into()]).map(drop)
    }
    fn is_moving(&mut self) -> Mach3Result<bool> {
        to_bool(&self.call("IsMoving", 0x22, Vec::new())?)
    }
    fn is_estop(&mut self) -> Mach3Result<bool> {
        to_bool(&self.call("IsEstop", 0xbd, Vec::new())?)
    }
}
