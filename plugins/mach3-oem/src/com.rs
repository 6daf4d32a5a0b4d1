//! The real Mach3, through COM (Windows only). Lives on the agent's Mach3 thread, which it
//! makes a single-threaded apartment; every call is made there (the agent queues them and
//! gives up waiting after its timeout).
//!
//! Attaches to the RUNNING Mach3 only (`GetActiveObject` by CLSID, which also works from a
//! 64-bit agent when the ProgID is registered only in the 32-bit view), never creates one:
//! that could start a second Mach3 without the machine's profile. When Mach3 goes away the
//! next call fails as "not running" and a later one attaches again (at most once a second).
//!
//! Written on `windows-sys` (plain function imports) rather than the `windows` crate: the
//! agent must load on Windows 7, and `windows-core` imports `combase.dll` and
//! `api-ms-win-core-winrt-error-l1-1-0.dll`, which Windows 7 lacks. Every import here is from
//! `ole32.dll` / `oleaut32.dll` and exists since Windows 2000; the two `IDispatch` methods
//! used are called through its vtable. Methods are found by name (`GetIDsOfNames`), with the
//! project's documented DISPID as the fallback; `GetVar`, which that list lacks, by name only.

use crate::mach3::{ErrorKind, Mach3, Mach3Error, Mach3Result};
use std::collections::HashMap;
use std::ffi::c_void;
use std::ptr::{null, null_mut, NonNull};
use std::time::{Duration, Instant};
use windows_sys::core::{GUID, HRESULT, PCWSTR};
use windows_sys::Win32::Foundation::SysAllocStringLen;
use windows_sys::Win32::System::Com::{
    CoInitializeEx, COINIT_APARTMENTTHREADED, DISPATCH_METHOD, DISPPARAMS,
};
use windows_sys::Win32::System::Ole::GetActiveObject;
use windows_sys::Win32::System::Variant::{
    VariantChangeType, VariantClear, VARENUM, VARIANT, VT_BOOL, VT_BSTR, VT_DISPATCH, VT_I2, VT_R8,
};

/// `Mach4.Document` (the historical name of Mach3's document object).
const CLSID_MACH4_DOCUMENT: GUID = GUID::from_u128(0xCA7992B2_2653_4342_8061_D7D385C07809);
const IID_IDISPATCH: GUID = GUID::from_u128(0x00020400_0000_0000_C000_000000000046);
const IID_NULL: GUID = GUID::from_u128(0);
const LOCALE_USER_DEFAULT: u32 = 0x0400;
const ATTACH_RETRY: Duration = Duration::from_secs(1);

/// HRESULTs that mean "Mach3 is not (or no longer) running", with their names for the log.
const GONE: [(u32, &str); 4] = [
    (0x800401E3, "MK_E_UNAVAILABLE"), // not in the running object table
    (0x80010108, "RPC_E_DISCONNECTED"),
    (0x800706BA, "RPC_S_SERVER_UNAVAILABLE"),
    (0x800401FD, "CO_E_OBJNOTCONNECTED"),
];

fn check(context: &str, hr: HRESULT) -> Mach3Result<()> {
    if hr >= 0 {
        return Ok(());
    }
    let code = hr as u32;
    let (kind, name) = match GONE.iter().find(|(c, _)| *c == code) {
        Some((_, name)) => (ErrorKind::NotRunning, *name),
        None => (ErrorKind::Com, "COM error"),
    };
    Err(Mach3Error::new(
        kind,
        format!("{context}: {name} (0x{code:08X})"),
    ))
}

/// `IUnknown`'s vtable: the three methods every COM object has first.
#[repr(C)]
struct UnknownVtbl {
    query_interface:
        unsafe extern "system" fn(*mut c_void, *const GUID, *mut *mut c_void) -> HRESULT,
    add_ref: unsafe extern "system" fn(*mut c_void) -> u32,
    release: unsafe extern "system" fn(*mut c_void) -> u32,
}

/// `IDispatch`'s vtable: IUnknown's, then its own four methods, in this order.
#[repr(C)]
struct DispatchVtbl {
    unknown: UnknownVtbl,
    _get_type_info_count: *const c_void,
    _get_type_info: *const c_void,
    get_ids_of_names: unsafe extern "system" fn(
        *mut c_void,
        *const GUID,
        *const PCWSTR,
        u32,
        u32,
        *mut i32,
    ) -> HRESULT,
    #[allow(clippy::type_complexity)]
    invoke: unsafe extern "system" fn(
        *mut c_void,
        i32,
        *const GUID,
        u32,
        u16,
        *const DISPPARAMS,
        *mut VARIANT,
        *mut c_void,
        *mut u32,
    ) -> HRESULT,
}

/// One counted reference to a COM object, released on drop.
struct Unknown(NonNull<c_void>);

impl Unknown {
    /// Takes over a reference the callee already counted (an out-parameter).
    fn from_owned(p: *mut c_void, what: &str) -> Mach3Result<Unknown> {
        NonNull::new(p)
            .map(Unknown)
            .ok_or_else(|| Mach3Error::new(ErrorKind::Com, format!("{what} returned nothing")))
    }

    fn vtbl(&self) -> &UnknownVtbl {
        // SAFETY: a COM object pointer points at its vtable pointer, whose first three slots
        // are IUnknown's; the object stays alive while this reference is counted.
        unsafe { &**(self.0.as_ptr() as *const *const UnknownVtbl) }
    }

    fn query_dispatch(&self, what: &str) -> Mach3Result<Dispatch> {
        let mut out = null_mut();
        // SAFETY: a valid IID and out-pointer; on success `out` holds a counted reference to
        // an object with IDispatch's vtable.
        let hr =
            unsafe { (self.vtbl().query_interface)(self.0.as_ptr(), &IID_IDISPATCH, &mut out) };
        check(&format!("{what} has no IDispatch"), hr)?;
        Unknown::from_owned(out, what).map(Dispatch)
    }
}

impl Clone for Unknown {
    fn clone(&self) -> Self {
        // SAFETY: counts one more reference to a live object; `Drop` releases it.
        unsafe { (self.vtbl().add_ref)(self.0.as_ptr()) };
        Unknown(self.0)
    }
}

impl Drop for Unknown {
    fn drop(&mut self) {
        // SAFETY: releases the one reference this value counted.
        unsafe { (self.vtbl().release)(self.0.as_ptr()) };
    }
}

/// A counted `IDispatch` (only made from a pointer known to be one: asked for by IID, or a
/// `VT_DISPATCH` result).
#[derive(Clone)]
struct Dispatch(Unknown);

impl Dispatch {
    fn ptr(&self) -> *mut c_void {
        self.0 .0.as_ptr()
    }

    fn vtbl(&self) -> &DispatchVtbl {
        // SAFETY: an IDispatch pointer points at IDispatch's vtable; the object stays alive
        // while this reference is counted.
        unsafe { &**(self.ptr() as *const *const DispatchVtbl) }
    }

    fn dispid(&self, name: &str) -> Mach3Result<i32> {
        let wide: Vec<u16> = name.encode_utf16().chain(Some(0)).collect();
        let names = [wide.as_ptr()];
        let mut id = 0i32;
        // SAFETY: one NUL-terminated name that outlives the call, one out DISPID.
        let hr = unsafe {
            (self.vtbl().get_ids_of_names)(
                self.ptr(),
                &IID_NULL,
                names.as_ptr(),
                1,
                LOCALE_USER_DEFAULT,
                &mut id,
            )
        };
        check(&format!("no method {name}"), hr)?;
        Ok(id)
    }

    fn invoke(&self, id: i32, mut args: Vec<Variant>) -> Mach3Result<Variant> {
        args.reverse(); // IDispatch::Invoke takes the last argument first
                        // `Variant` is a transparent VARIANT, so the vector is the argument array.
        let params = DISPPARAMS {
            rgvarg: args.as_mut_ptr() as *mut VARIANT,
            rgdispidNamedArgs: null_mut(),
            cArgs: args.len() as u32,
            cNamedArgs: 0,
        };
        let mut result = Variant::empty();
        // SAFETY: `params` points into `args`, which outlives the call; `result` is an out
        // VARIANT; no exception info or argument error index is asked for.
        let hr = unsafe {
            (self.vtbl().invoke)(
                self.ptr(),
                id,
                &IID_NULL,
                LOCALE_USER_DEFAULT,
                DISPATCH_METHOD,
                &params,
                &mut result.0,
                null_mut(),
                null_mut(),
            )
        };
        check("call failed", hr)?;
        Ok(result)
    }
}

/// An owned VARIANT, cleared (its string freed, its object released) on drop.
#[repr(transparent)]
struct Variant(VARIANT);

impl Variant {
    fn empty() -> Variant {
        Variant(VARIANT::default()) // all zero: VT_EMPTY
    }

    fn of(vt: VARENUM, set: impl FnOnce(&mut VARIANT)) -> Variant {
        let mut v = Variant::empty();
        set(&mut v.0);
        // Set last, so a half-built VARIANT is never cleared as the type it is not yet.
        v.0.Anonymous.Anonymous.vt = vt;
        v
    }

    fn i16(x: i16) -> Variant {
        Variant::of(VT_I2, |v| v.Anonymous.Anonymous.Anonymous.iVal = x)
    }

    fn f64(x: f64) -> Variant {
        Variant::of(VT_R8, |v| v.Anonymous.Anonymous.Anonymous.dblVal = x)
    }

    fn string(s: &str) -> Mach3Result<Variant> {
        let wide: Vec<u16> = s.encode_utf16().collect();
        // SAFETY: copies `wide.len()` UTF-16 units into a new BSTR (the VARIANT owns it).
        let bstr = unsafe { SysAllocStringLen(wide.as_ptr(), wide.len() as u32) };
        if bstr.is_null() {
            return Err(Mach3Error::new(ErrorKind::Com, "SysAllocStringLen failed"));
        }
        Ok(Variant::of(VT_BSTR, |v| {
            v.Anonymous.Anonymous.Anonymous.bstrVal = bstr
        }))
    }

    fn vt(&self) -> VARENUM {
        // SAFETY: every VARIANT starts with its type tag.
        unsafe { self.0.Anonymous.Anonymous.vt }
    }

    /// This value converted by OLE's own rules (as VBScript would), e.g. a string DRO.
    fn converted(&self, vt: VARENUM, what: &str) -> Mach3Result<Variant> {
        let mut out = Variant::empty();
        // SAFETY: both are valid VARIANTs; `out` receives a value it then owns.
        let hr = unsafe { VariantChangeType(&mut out.0, &self.0, 0, vt) };
        check(what, hr)?;
        Ok(out)
    }

    fn to_f64(&self) -> Mach3Result<f64> {
        let v = self.converted(VT_R8, "not a number")?;
        // SAFETY: `v` is a VT_R8.
        Ok(unsafe { v.0.Anonymous.Anonymous.Anonymous.dblVal })
    }

    fn to_bool(&self) -> Mach3Result<bool> {
        let v = self.converted(VT_BOOL, "not a boolean")?;
        // SAFETY: `v` is a VT_BOOL (VARIANT_TRUE is -1, VARIANT_FALSE 0).
        Ok(unsafe { v.0.Anonymous.Anonymous.Anonymous.boolVal } != 0)
    }

    fn to_dispatch(&self, what: &str) -> Mach3Result<Dispatch> {
        if self.vt() != VT_DISPATCH {
            return Err(Mach3Error::new(
                ErrorKind::Com,
                format!(
                    "{what} returned a VARIANT of type {}, not an object",
                    self.vt()
                ),
            ));
        }
        // SAFETY: a VT_DISPATCH holds an IDispatch pointer (maybe null).
        let p = unsafe { self.0.Anonymous.Anonymous.Anonymous.pdispVal };
        let d = NonNull::new(p)
            .map(|p| Dispatch(Unknown(p)))
            .ok_or_else(|| Mach3Error::new(ErrorKind::Com, format!("{what} returned no object")))?;
        // The VARIANT keeps (and on drop releases) its own reference: count ours.
        let ours = d.clone();
        std::mem::forget(d);
        Ok(ours)
    }
}

impl Drop for Variant {
    fn drop(&mut self) {
        // SAFETY: clears a valid VARIANT once (frees its BSTR, releases its object).
        unsafe { VariantClear(&mut self.0) };
    }
}

/// `IMyScriptObject` of the running Mach3.
pub struct ComMach3 {
    script: Option<Dispatch>,
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
        let hr = unsafe { CoInitializeEx(null(), COINIT_APARTMENTTHREADED as u32) };
        if let Err(e) = check("CoInitializeEx", hr) {
            eprintln!("fresa-mach3-agent: {}", e.message);
        }
        ComMach3 {
            script: None,
            dispids: HashMap::new(),
            next_attach: Instant::now(),
            last_error: Mach3Error::new(ErrorKind::NotRunning, "not attached yet"),
        }
    }

    fn attach() -> Mach3Result<Dispatch> {
        let mut unknown = null_mut();
        // SAFETY: valid pointers to a GUID and an out-parameter that lives across the call.
        let hr = unsafe { GetActiveObject(&CLSID_MACH4_DOCUMENT, null_mut(), &mut unknown) };
        check("Mach3 (Mach4.Document) is not running in this session", hr)?;
        let unknown = Unknown::from_owned(unknown, "GetActiveObject")?;
        let document = unknown.query_dispatch("Mach4.Document")?;
        let id = document.dispid("GetScriptDispatch")?;
        document
            .invoke(id, Vec::new())?
            .to_dispatch("GetScriptDispatch")
    }

    fn script(&mut self) -> Mach3Result<Dispatch> {
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
        args: Vec<Variant>,
    ) -> Mach3Result<Variant> {
        self.invoke(name, Some(fallback), args)
    }

    /// Calls a method that has no documented DISPID: found by name only (`GetIDsOfNames` on
    /// the object itself), or the error says Mach3 has no such method.
    fn call_by_name(&mut self, name: &'static str, args: Vec<Variant>) -> Mach3Result<Variant> {
        self.invoke(name, None, args)
    }

    fn invoke(
        &mut self,
        name: &'static str,
        fallback: Option<i32>,
        args: Vec<Variant>,
    ) -> Mach3Result<Variant> {
        let script = self.script()?;
        let id = match self.dispids.get(name) {
            Some(id) => *id,
            None => {
                let id = match (script.dispid(name), fallback) {
                    (Ok(id), _) => id,
                    (Err(_), Some(id)) => id,
                    (Err(e), None) => {
                        if e.kind == ErrorKind::NotRunning {
                            self.script = None;
                        }
                        return Err(Mach3Error::new(
                            e.kind,
                            format!("this Mach3's script object has no {name}: {}", e.message),
                        ));
                    }
                };
                self.dispids.insert(name, id);
                id
            }
        };
        script.invoke(id, args).map_err(|e| {
            if e.kind == ErrorKind::NotRunning {
                self.script = None; // Mach3 went away: attach again next time
            }
            Mach3Error::new(e.kind, format!("{name}: {}", e.message))
        })
    }
}

impl Mach3 for ComMach3 {
    fn do_oem_button(&mut self, code: i16) -> Mach3Result<()> {
        self.call("DoOEMButton", 0x28, vec![Variant::i16(code)])
            .map(drop)
    }
    fn get_oem_dro(&mut self, code: i16) -> Mach3Result<f64> {
        self.call("GetOEMDRO", 0x2d, vec![Variant::i16(code)])?
            .to_f64()
    }
    fn set_oem_dro(&mut self, code: i16, value: f64) -> Mach3Result<()> {
        self.call(
            "SetOEMDRO",
            0x30,
            vec![Variant::i16(code), Variant::f64(value)],
        )
        .map(drop)
    }
    fn get_oem_led(&mut self, code: i16) -> Mach3Result<bool> {
        self.call("GetOEMLed", 0x2c, vec![Variant::i16(code)])?
            .to_bool()
    }
    fn code(&mut self, line: &str) -> Mach3Result<()> {
        self.call("Code", 0x1c, vec![Variant::string(line)?])
            .map(drop)
    }
    fn load_file(&mut self, path: &str) -> Mach3Result<()> {
        self.call("LoadFile", 0x88, vec![Variant::string(path)?])
            .map(drop)
    }
    fn jog_on(&mut self, axis: i16, direction: i16) -> Mach3Result<()> {
        self.call(
            "JogOn",
            0x8b,
            vec![Variant::i16(axis), Variant::i16(direction)],
        )
        .map(drop)
    }
    fn jog_off(&mut self, axis: i16) -> Mach3Result<()> {
        self.call("JogOff", 0x8c, vec![Variant::i16(axis)])
            .map(drop)
    }
    fn is_moving(&mut self) -> Mach3Result<bool> {
        self.call("IsMoving", 0x22, Vec::new())?.to_bool()
    }
    fn is_estop(&mut self) -> Mach3Result<bool> {
        self.call("IsEstop", 0xbd, Vec::new())?.to_bool()
    }
    fn get_var(&mut self, var: i16) -> Mach3Result<f64> {
        // Mach3's macros call it as `GetVar(2002)`; IDispatch converts the short as they do.
        self.call_by_name("GetVar", vec![Variant::i16(var)])?
            .to_f64()
    }
}
