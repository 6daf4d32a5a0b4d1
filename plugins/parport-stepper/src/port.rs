//! The parallel port behind a trait: the real one through Linux `ppdev`, and a simulated one
//! that records every write with its time and serves scripted input levels.

use crate::pins;
use std::io;
use std::time::Instant;

/// The three registers of a parallel port.
pub trait Port: Send {
    fn write_data(&mut self, value: u8) -> io::Result<()>;
    fn write_control(&mut self, value: u8) -> io::Result<()>;
    fn read_status(&mut self) -> io::Result<u8>;
    /// The output loop starts tick `index` (only the simulated port cares).
    fn begin_tick(&mut self, _index: u64) {}
}

/// Which register a recorded write went to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Register {
    Data,
    Control,
}

/// One write seen by [`SimPort`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Write {
    pub tick: u64,
    pub at: Instant,
    pub register: Register,
    pub value: u8,
}

/// A scripted input change: after the port has seen `after_writes` data-register writes, input
/// `pin` goes to `level` (electrical, true = high).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ScriptedInput {
    pub after_writes: u64,
    pub pin: u8,
    pub level: bool,
}

/// A simulated port. Deterministic: inputs change on write counts, not on time.
#[derive(Debug)]
pub struct SimPort {
    tick: u64,
    data_writes: u64,
    levels: Vec<(u8, bool)>,
    script: Vec<ScriptedInput>,
    /// Every write, or only the last `keep` when bounded.
    pub writes: std::collections::VecDeque<Write>,
    keep: usize,
    /// Tick at which each status read returned a value that differs from the previous read.
    pub status_changes: Vec<(u64, u8)>,
    last_status: Option<u8>,
}

impl SimPort {
    /// `initial` input levels; `script` sorted or not; `keep` = how many writes to remember.
    pub fn new(initial: Vec<(u8, bool)>, mut script: Vec<ScriptedInput>, keep: usize) -> SimPort {
        script.sort_by_key(|s| s.after_writes);
        SimPort {
            tick: 0,
            data_writes: 0,
            levels: initial,
            script,
            writes: Default::default(),
            keep,
            status_changes: Vec::new(),
            last_status: None,
        }
    }

    fn record(&mut self, register: Register, value: u8) {
        if self.writes.len() == self.keep {
            self.writes.pop_front();
        }
        self.writes.push_back(Write {
            tick: self.tick,
            at: Instant::now(),
            register,
            value,
        });
    }

    fn set_level(&mut self, pin: u8, level: bool) {
        match self.levels.iter_mut().find(|(p, _)| *p == pin) {
            Some(l) => l.1 = level,
            None => self.levels.push((pin, level)),
        }
    }
}

impl Port for SimPort {
    fn write_data(&mut self, value: u8) -> io::Result<()> {
        self.record(Register::Data, value);
        self.data_writes += 1;
        while let Some(s) = self.script.first().copied() {
            if s.after_writes > self.data_writes {
                break;
            }
            self.script.remove(0);
            self.set_level(s.pin, s.level);
        }
        Ok(())
    }

    fn write_control(&mut self, value: u8) -> io::Result<()> {
        self.record(Register::Control, value);
        Ok(())
    }

    fn read_status(&mut self) -> io::Result<u8> {
        let v = pins::status_register(self.levels.iter().copied());
        if self.last_status != Some(v) {
            self.status_changes.push((self.tick, v));
            self.last_status = Some(v);
        }
        Ok(v)
    }

    fn begin_tick(&mut self, index: u64) {
        self.tick = index;
    }
}

/// A shared handle on a [`SimPort`], so tests can inspect what the output loop wrote.
#[derive(Debug, Clone)]
pub struct SharedSimPort(pub std::sync::Arc<std::sync::Mutex<SimPort>>);

impl SharedSimPort {
    pub fn lock(&self) -> std::sync::MutexGuard<'_, SimPort> {
        self.0.lock().unwrap_or_else(|e| e.into_inner())
    }
}

impl Port for SharedSimPort {
    fn write_data(&mut self, value: u8) -> io::Result<()> {
        self.lock().write_data(value)
    }
    fn write_control(&mut self, value: u8) -> io::Result<()> {
        self.lock().write_control(value)
    }
    fn read_status(&mut self) -> io::Result<u8> {
        self.lock().read_status()
    }
    fn begin_tick(&mut self, index: u64) {
        self.lock().begin_tick(index)
    }
}

#[cfg(target_os = "linux")]
pub use ppdev::Ppdev;

#[cfg(target_os = "linux")]
pub mod ppdev {
    //! Linux `ppdev`: `/dev/parportN`, claimed exclusively, registers through ioctls.

    use super::Port;
    use std::fs::{File, OpenOptions};
    use std::io;
    use std::os::fd::AsRawFd;
    use std::path::Path;

    // ioctl numbers of <linux/ppdev.h> (`_IO`/`_IOR`/`_IOW` on type 'p'); a test compiles the
    // system header with the C compiler and checks these against it.
    const fn ioc(dir: u64, nr: u64, size: u64) -> u64 {
        (dir << 30) | (size << 16) | ((b'p' as u64) << 8) | nr
    }
    const NONE: u64 = 0;
    const WRITE: u64 = 1;
    const READ: u64 = 2;
    pub const PPCLAIM: u64 = ioc(NONE, 0x8b, 0);
    pub const PPRELEASE: u64 = ioc(NONE, 0x8c, 0);
    pub const PPEXCL: u64 = ioc(NONE, 0x8f, 0);
    pub const PPRSTATUS: u64 = ioc(READ, 0x81, 1);
    pub const PPWCONTROL: u64 = ioc(WRITE, 0x84, 1);
    pub const PPWDATA: u64 = ioc(WRITE, 0x86, 1);

    /// A claimed parallel port.
    pub struct Ppdev {
        file: File,
    }

    fn ioctl(file: &File, request: u64, arg: *mut u8) -> io::Result<()> {
        // SAFETY: `file` is an open ppdev descriptor and `arg` points to one byte (or is null
        // for the argument-less requests), which is what these requests read or write.
        let r = unsafe { libc::ioctl(file.as_raw_fd(), request as _, arg) };
        if r < 0 {
            Err(io::Error::last_os_error())
        } else {
            Ok(())
        }
    }

    impl Ppdev {
        /// Opens and claims the port exclusively (PPEXCL must come before PPCLAIM).
        pub fn open(path: &Path) -> io::Result<Ppdev> {
            let file = OpenOptions::new().read(true).write(true).open(path)?;
            ioctl(&file, PPEXCL, std::ptr::null_mut()).map_err(|e| {
                io::Error::new(e.kind(), format!("PPEXCL (exclusive access) failed: {e}"))
            })?;
            ioctl(&file, PPCLAIM, std::ptr::null_mut())
                .map_err(|e| io::Error::new(e.kind(), format!("PPCLAIM failed: {e}")))?;
            Ok(Ppdev { file })
        }
    }

    impl Port for Ppdev {
        fn write_data(&mut self, value: u8) -> io::Result<()> {
            let mut v = value;
            ioctl(&self.file, PPWDATA, &mut v)
        }
        fn write_control(&mut self, value: u8) -> io::Result<()> {
            let mut v = value;
            ioctl(&self.file, PPWCONTROL, &mut v)
        }
        fn read_status(&mut self) -> io::Result<u8> {
            let mut v = 0u8;
            ioctl(&self.file, PPRSTATUS, &mut v)?;
            Ok(v)
        }
    }

    impl Drop for Ppdev {
        fn drop(&mut self) {
            // Leave the coils off and give the port back.
            let _ = self.write_data(0);
            let _ = ioctl(&self.file, PPRELEASE, std::ptr::null_mut());
        }
    }
}
