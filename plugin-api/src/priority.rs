//! Scheduling priority for a plugin's own threads whose latency an operator feels (a
//! pendant's link, the parallel port's step loop). Linux keeps a nice value per thread, so
//! raising one thread leaves the rest of the server as it is; Windows has thread priorities
//! within the process's class.

/// Sets the calling thread's nice value (-20 highest, 19 lowest). On Linux, lowering it below
/// 0 needs `CAP_SYS_NICE` or an `RLIMIT_NICE` that allows it (systemd: `LimitNICE=`); Err says
/// why not, and the thread keeps its priority. On Windows the thread's priority within the
/// normal class stands in for it (-15 and below: highest, -5 and below: above normal, 5 and
/// above: below normal), which needs no privilege.
pub fn set_thread_nice(nice: i32) -> Result<(), String> {
    #[cfg(target_os = "linux")]
    {
        // SAFETY: a plain syscall naming the calling thread by its id; no memory is passed.
        let r =
            unsafe { libc::setpriority(libc::PRIO_PROCESS, libc::gettid() as libc::id_t, nice) };
        if r == 0 {
            Ok(())
        } else {
            Err(std::io::Error::last_os_error().to_string())
        }
    }
    #[cfg(windows)]
    {
        use windows_sys::Win32::System::Threading::{
            GetCurrentThread, SetThreadPriority, THREAD_PRIORITY_ABOVE_NORMAL,
            THREAD_PRIORITY_BELOW_NORMAL, THREAD_PRIORITY_HIGHEST, THREAD_PRIORITY_NORMAL,
        };
        let priority = match nice {
            ..=-15 => THREAD_PRIORITY_HIGHEST,
            -14..=-5 => THREAD_PRIORITY_ABOVE_NORMAL,
            -4..=4 => THREAD_PRIORITY_NORMAL,
            _ => THREAD_PRIORITY_BELOW_NORMAL,
        };
        // SAFETY: the pseudo-handle of the calling thread, valid for the call.
        if unsafe { SetThreadPriority(GetCurrentThread(), priority) } != 0 {
            Ok(())
        } else {
            Err(std::io::Error::last_os_error().to_string())
        }
    }
    #[cfg(not(any(target_os = "linux", windows)))]
    {
        let _ = nice;
        Err("thread priorities are only set on Linux and Windows".into())
    }
}

/// The calling thread's nice value as the kernel reports it (`/proc/thread-self/stat`), for
/// tests and logs. None where that file does not exist.
pub fn thread_nice() -> Option<i32> {
    nice_in_stat(&std::fs::read_to_string("/proc/thread-self/stat").ok()?)
}

/// The nice value in the text of a Linux `/proc/.../stat` file (a process's or a thread's).
pub fn nice_in_stat(stat: &str) -> Option<i32> {
    // Field 19 (nice), counted from 1; the command name (field 2) may hold spaces and `)`, so
    // count from the last `)`, the one that ends it.
    let after_name = stat.get(stat.rfind(')')? + 2..)?;
    after_name.split(' ').nth(16)?.parse().ok()
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[cfg(target_os = "linux")]
    #[test]
    fn a_thread_can_always_lower_its_own_priority_and_reads_it_back() {
        // Raising a nice value (less priority) needs no permission; the other threads of the
        // process keep theirs.
        let before = thread_nice().unwrap();
        let nice = std::thread::spawn(|| {
            set_thread_nice(5).unwrap();
            thread_nice().unwrap()
        })
        .join()
        .unwrap();
        assert_eq!(nice, 5);
        assert_eq!(thread_nice().unwrap(), before);
    }

    #[test]
    fn the_nice_value_is_read_after_a_command_name_that_holds_spaces_and_parentheses() {
        let stat = "4242 (a (b) c) S 1 4242 4242 0 -1 4194560 600 0 0 0 5 3 0 0 20 -10 3 0 \
                    12345 1000000 250";
        assert_eq!(nice_in_stat(stat), Some(-10));
        assert_eq!(nice_in_stat("4242 (x) S 1"), None);
    }

    #[cfg(windows)]
    use windows_sys::Win32::System::Threading::{
        GetCurrentThread, GetThreadPriority, THREAD_PRIORITY_ABOVE_NORMAL, THREAD_PRIORITY_HIGHEST,
    };

    #[cfg(windows)]
    #[test]
    fn a_nice_value_becomes_the_threads_priority_in_its_class() {
        let got = std::thread::spawn(|| {
            set_thread_nice(-10).unwrap();
            // SAFETY: the calling thread's pseudo-handle.
            let above = unsafe { GetThreadPriority(GetCurrentThread()) };
            set_thread_nice(-20).unwrap();
            (above, unsafe { GetThreadPriority(GetCurrentThread()) })
        })
        .join()
        .unwrap();
        assert_eq!(got, (THREAD_PRIORITY_ABOVE_NORMAL, THREAD_PRIORITY_HIGHEST));
    }
}
