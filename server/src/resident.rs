//! Once `fresa serve` is ready, it unmaps the pages of files it has mapped read-only (its own
//! binary, the plugins, the C library) that the start touched (Linux). The start runs code the
//! idle server never runs again (the routing table with each route's OpenAPI operation, the
//! migrations, loading every plugin), and the kernel maps a file's pages around each fault in
//! large blocks: 12 MiB of the binary's 16 MiB of code stayed mapped, while an idle server
//! touches about 2 MiB of it in 10 s (`cargo bench -p fresa-tests --bench startup`).
//!
//! `MADV_DONTNEED` on a private mapping of a file that holds no modified page drops only the
//! page-table entries: the pages stay in the page cache, and the next access maps the same
//! bytes back (a minor fault). So the resident set counts what the server goes on using, and
//! under memory pressure the kernel can reclaim what only the start used first (it keeps
//! mapped code longer than unmapped pages). Nothing is freed that another process shares.
//!
//! The OpenAPI document's first request builds the routing table again (`fresa_http::openapi`);
//! after it, only the binary's own pages are unmapped ([`Files::Binary`]), since machines may
//! be moving by then.

use std::io::BufRead;

/// Which files' pages [`unmap_pages_used_once`] unmaps.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Files {
    /// Every file mapped read-only: the binary, the plugins, the libraries. For the start,
    /// which loads the plugins and ends before any of them can move a machine.
    All,
    /// The `fresa` binary only (as `/proc/self/exe` names it). For work that ran only the
    /// binary's code and may come while a plugin's real-time loop (the parallel port's step
    /// output) runs: its code, in the plugin and the C library, must not fault back in under it.
    Binary,
}

/// Unmaps the pages of the process's unmodified read-only mappings of `files`, once `work` that
/// ran code nothing else runs is done (`"start"`: the start; `"describing the API"`: the
/// OpenAPI document's first request, which builds the routing table again); logs what it did
/// at DEBUG. Blocking (reads `/proc/self/smaps`): call it off the runtime's workers.
pub fn unmap_pages_used_once(work: &'static str, files: Files) {
    match unmap_read_only_file_pages(files) {
        Ok(kib) => tracing::debug!(kib, work, ?files, "unmapped the pages of read-only files"),
        Err(e) => {
            tracing::debug!(error = %e, work, ?files, "could not read which pages to unmap");
        }
    }
}

/// What [`unmap_pages_used_once`] does: the KiB that were resident in the mappings it dropped.
/// A mapping the kernel refuses to drop (one of a device, say) is left as it is.
fn unmap_read_only_file_pages(files: Files) -> std::io::Result<u64> {
    let only = match files {
        Files::All => None,
        Files::Binary => Some(std::fs::read_link("/proc/self/exe")?),
    };
    // Read line by line: the whole text is a few hundred KiB the allocator would then keep.
    let smaps = std::io::BufReader::new(std::fs::File::open("/proc/self/smaps")?);
    let mut dropped = 0;
    for m in droppable(smaps, only.as_deref())? {
        // SAFETY: the range is one of this process's private file mappings (page-aligned, as
        // every mapping is) that is not writable and held no anonymous (modified) page when
        // smaps was read; without write access none can appear since. Every page there is the
        // file's page-cache page, so dropping the entries changes no byte that code or data
        // reads: the next access maps the same page back. No mapping is moved or unmapped.
        let r = unsafe {
            libc::madvise(
                m.start as *mut libc::c_void,
                m.end - m.start,
                libc::MADV_DONTNEED,
            )
        };
        if r == 0 {
            dropped += m.rss_kib.unwrap_or(0);
        }
    }
    Ok(dropped)
}

/// One mapping of `/proc/self/smaps`, as far as this module needs it.
#[derive(Debug, PartialEq)]
struct Mapping {
    start: usize,
    end: usize,
    /// Whether it can be dropped by what its first line says: of a file, not writable.
    read_only_file: bool,
    /// The file's path as smaps gives it (blanks kept), or `[stack]`, `[vdso]`, empty.
    path: String,
    rss_kib: Option<u64>,
    anonymous_kib: Option<u64>,
}

/// The mappings that can be dropped: of a file (of `only`, if given), not writable, with no
/// anonymous page (a relocated read-only segment, or code a debugger patched, has some),
/// something resident.
fn droppable(smaps: impl BufRead, only: Option<&std::path::Path>) -> std::io::Result<Vec<Mapping>> {
    let mut all: Vec<Mapping> = Vec::new();
    for line in smaps.lines() {
        let line = line?;
        if let Some(m) = header(&line) {
            all.push(m);
        } else if let Some(m) = all.last_mut() {
            let mut fields = line.split_whitespace();
            let field = fields.next();
            let kib = fields.next().and_then(|v| v.parse().ok());
            match field {
                Some("Rss:") => m.rss_kib = kib,
                Some("Anonymous:") => m.anonymous_kib = kib,
                _ => {}
            }
        }
    }
    all.retain(|m| {
        m.read_only_file
            && m.anonymous_kib == Some(0)
            && m.rss_kib.is_some_and(|kib| kib > 0)
            && only.is_none_or(|file| file.as_os_str() == m.path.as_str())
    });
    Ok(all)
}

/// A mapping's first line, `start-end perms offset dev inode [path]`; None for the field lines
/// (`Name: value`) under it.
fn header(line: &str) -> Option<Mapping> {
    fn field(s: &str) -> (&str, &str) {
        let s = s.trim_start();
        s.split_once(' ').unwrap_or((s, ""))
    }
    let (range, rest) = field(line);
    let (start, end) = range.split_once('-')?;
    let start = usize::from_str_radix(start, 16).ok()?;
    let end = usize::from_str_radix(end, 16).ok()?;
    let (perms, rest) = field(rest);
    let (_offset, rest) = field(rest);
    let (_device, rest) = field(rest);
    let (_inode, path) = field(rest);
    let path = path.trim_start();
    // The path may hold blanks; anonymous memory has none, the stack and vDSO a `[name]`.
    Some(Mapping {
        start,
        end,
        read_only_file: !perms.contains('w') && path.starts_with('/'),
        path: path.to_string(),
        rss_kib: None,
        anonymous_kib: None,
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    const SMAPS: &str = "\
5555a000-5555b000 r--p 00000000 fd:00 42        /opt/fresa bin/fresa
Size:                  4 kB
Rss:                   4 kB
Anonymous:             0 kB
VmFlags: rd mr mw me dw sd
5555b000-5555f000 r-xp 00001000 fd:00 42        /opt/fresa bin/fresa
Rss:                  12 kB
Anonymous:             0 kB
5555f000-55560000 r--p 00005000 fd:00 42        /opt/fresa bin/fresa
Rss:                   4 kB
Anonymous:             4 kB
55560000-55561000 rw-p 00006000 fd:00 42        /opt/fresa bin/fresa
Rss:                   4 kB
Anonymous:             0 kB
55561000-55562000 r-xp 00000000 fd:00 43        /usr/lib/libc.so.6
Rss:                   4 kB
Anonymous:             0 kB
55562000-55563000 r-xp 00000000 fd:00 44        /usr/lib/libunused.so
Rss:                   0 kB
Anonymous:             0 kB
55563000-55564000 r--p 00000000 00:00 0
Rss:                   4 kB
Anonymous:             0 kB
7fff0000-7fff1000 rw-p 00000000 00:00 0          [stack]
Rss:                   4 kB
Anonymous:             4 kB
7fff2000-7fff3000 r-xp 00000000 00:00 0          [vdso]
Rss:                   4 kB
Anonymous:             0 kB
";

    /// Only read-only, unmodified, resident mappings of files: not the relocated read-only
    /// one (anonymous pages), not a writable one, not one with nothing resident, not a
    /// mapping with no file (anonymous memory, the stack, the vDSO).
    #[test]
    fn only_unmodified_read_only_file_mappings_are_dropped() {
        let found = |only: Option<&str>| -> Vec<_> {
            droppable(SMAPS.as_bytes(), only.map(std::path::Path::new))
                .unwrap()
                .into_iter()
                .map(|m| (m.start, m.end, m.path, m.rss_kib))
                .collect()
        };
        let fresa = || "/opt/fresa bin/fresa".to_string();
        assert_eq!(
            found(None),
            [
                (0x5555a000, 0x5555b000, fresa(), Some(4)),
                (0x5555b000, 0x5555f000, fresa(), Some(12)),
                (0x55561000, 0x55562000, "/usr/lib/libc.so.6".into(), Some(4)),
            ]
        );
        // Only the binary's (`Files::Binary`): the library is left mapped.
        assert_eq!(
            found(Some("/opt/fresa bin/fresa")),
            [
                (0x5555a000, 0x5555b000, fresa(), Some(4)),
                (0x5555b000, 0x5555f000, fresa(), Some(12)),
            ]
        );
    }

    /// Resident KiB of the droppable mappings: of this process's own binary, and of the rest.
    fn resident_kib_of_droppable() -> (u64, u64) {
        let exe = std::fs::read_link("/proc/self/exe").unwrap();
        let smaps = std::fs::read("/proc/self/smaps").unwrap();
        let mut kib = (0, 0);
        for m in droppable(smaps.as_slice(), None).unwrap() {
            let resident = m.rss_kib.unwrap_or(0);
            if exe.as_os_str() == m.path.as_str() {
                kib.0 += resident;
            } else {
                kib.1 += resident;
            }
        }
        kib
    }

    /// In this process (the test binary): the pages go, and the code still runs (it is mapped
    /// back from the page cache as it is reached). `Files::Binary` leaves the libraries'
    /// pages mapped; `Files::All` drops them too. One test: the two must not run at once.
    #[test]
    fn read_only_file_pages_are_unmapped_and_come_back_as_they_are_used() {
        let (binary, libraries) = resident_kib_of_droppable();
        assert!(binary > 0 && libraries > 0, "{binary} KiB, {libraries} KiB");
        let dropped = unmap_read_only_file_pages(Files::Binary).unwrap();
        assert!(dropped >= binary / 2, "dropped {dropped} KiB of {binary}");
        // Reading smaps again runs code (mapped back): still less than before.
        let after = resident_kib_of_droppable();
        assert!(
            after.0 < binary,
            "binary: {after:?} KiB after, {binary} before"
        );
        assert!(
            after.1 >= libraries,
            "libraries: {after:?} KiB after, {libraries} before"
        );
        let dropped = unmap_read_only_file_pages(Files::All).unwrap();
        assert!(dropped >= after.1, "dropped {dropped} KiB of {after:?}");
        let after_all = resident_kib_of_droppable();
        assert!(
            after_all.1 < libraries,
            "{after_all:?} KiB after, {libraries} before"
        );
    }
}
