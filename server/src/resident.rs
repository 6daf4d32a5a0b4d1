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

use std::io::BufRead;

/// Unmaps the pages of the process's unmodified read-only file mappings, once `work` that ran
/// code nothing else runs is done (`"start"`: the start; `"describing the API"`: the OpenAPI
/// document's first request, which builds the routing table again); logs what it did at DEBUG.
/// Blocking (reads `/proc/self/smaps`): call it off the runtime's workers.
pub fn unmap_pages_used_once(work: &'static str) {
    match unmap_read_only_file_pages() {
        Ok(kib) => tracing::debug!(kib, work, "unmapped the pages of read-only files"),
        Err(e) => tracing::debug!(error = %e, work, "could not read which pages to unmap"),
    }
}

/// What [`unmap_pages_used_once`] does: the KiB that were resident in the mappings it dropped.
/// A mapping the kernel refuses to drop (one of a device, say) is left as it is.
fn unmap_read_only_file_pages() -> std::io::Result<u64> {
    // Read line by line: the whole text is a few hundred KiB the allocator would then keep.
    let smaps = std::io::BufReader::new(std::fs::File::open("/proc/self/smaps")?);
    let mut dropped = 0;
    for m in droppable(smaps)? {
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
    rss_kib: Option<u64>,
    anonymous_kib: Option<u64>,
}

/// The mappings that can be dropped: of a file, not writable, with no anonymous page (a
/// relocated read-only segment, or code a debugger patched, has some), something resident.
fn droppable(smaps: impl BufRead) -> std::io::Result<Vec<Mapping>> {
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
        m.read_only_file && m.anonymous_kib == Some(0) && m.rss_kib.is_some_and(|kib| kib > 0)
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
    // The path may hold blanks; anonymous memory has none, the stack and vDSO a `[name]`.
    Some(Mapping {
        start,
        end,
        read_only_file: !perms.contains('w') && path.trim_start().starts_with('/'),
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
        let found: Vec<_> = droppable(SMAPS.as_bytes())
            .unwrap()
            .into_iter()
            .map(|m| (m.start, m.end, m.rss_kib))
            .collect();
        assert_eq!(
            found,
            [
                (0x5555a000, 0x5555b000, Some(4)),
                (0x5555b000, 0x5555f000, Some(12)),
                (0x55561000, 0x55562000, Some(4)),
            ]
        );
    }

    fn resident_kib_of_droppable() -> u64 {
        let smaps = std::fs::read("/proc/self/smaps").unwrap();
        let found = droppable(smaps.as_slice()).unwrap();
        found.iter().filter_map(|m| m.rss_kib).sum()
    }

    /// In this process (the test binary): the pages go, and the code still runs (it is mapped
    /// back from the page cache as it is reached).
    #[test]
    fn read_only_file_pages_are_unmapped_and_come_back_as_they_are_used() {
        let before = resident_kib_of_droppable();
        assert!(before > 0, "nothing read-only of a file is resident");
        let dropped = unmap_read_only_file_pages().unwrap();
        assert!(dropped >= before / 2, "dropped {dropped} KiB of {before}");
        // Reading smaps again runs code (mapped back): still less than before.
        let after = resident_kib_of_droppable();
        assert!(
            after < before,
            "resident {after} KiB after, {before} before"
        );
    }
}
