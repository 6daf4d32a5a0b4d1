//! The daemon's allocator on Linux: mimalloc, called directly. The `mimalloc` crate asks
//! `mi_malloc_aligned` for every block, whose fast path holds only for small blocks whose free
//! slot happens to be aligned, and whose generic path (every block over 1 KiB) over-allocates
//! and searches; that was 1,400 instructions of a status request. Every mimalloc block is
//! aligned to at least a pointer's size, so a layout asking no more than that (nearly all of
//! Rust's) takes the plain calls, and only a larger alignment the aligned ones.

use libmimalloc_sys as mi;
use std::alloc::{GlobalAlloc, Layout};
use std::ffi::c_void;

/// The alignment every mimalloc block has: its block sizes are whole words, and its pages
/// start aligned to 16 bytes.
const EVERY_BLOCK_ALIGN: usize = std::mem::size_of::<usize>();

pub struct MiMalloc;

/// Whether every mimalloc block already has the layout's alignment, so the plain calls serve it.
#[inline(always)]
fn plain_call_aligns(layout: Layout) -> bool {
    layout.align() <= EVERY_BLOCK_ALIGN
}

/// Gives the calling thread's free pages back to the system now. For a thread that built
/// something large and is done allocating (the routing table, whose OpenAPI scaffolding is
/// dropped at once; the OpenAPI document, described on its first request): mimalloc keeps a
/// thread's freed pages in its heap, even after the thread has ended, and they showed as up to
/// 1 MiB more idle memory (1.4 MiB after the document).
pub fn release_thread_garbage() {
    // SAFETY: takes no pointers; collects only the calling thread's own heap.
    unsafe { mi::mi_collect(true) }
}

// SAFETY: each call passes the layout's size (and, above `EVERY_BLOCK_ALIGN`, its alignment) to
// mimalloc, which returns null or a block of at least that size and alignment; blocks are
// freed and resized only with pointers it returned (`GlobalAlloc`'s contract on the caller).
unsafe impl GlobalAlloc for MiMalloc {
    #[inline]
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // SAFETY: see the impl.
        unsafe { block(layout, mi::mi_malloc, mi::mi_malloc_aligned) }
    }

    #[inline]
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        // SAFETY: see the impl.
        unsafe { block(layout, mi::mi_zalloc, mi::mi_zalloc_aligned) }
    }

    #[inline]
    unsafe fn dealloc(&self, ptr: *mut u8, _layout: Layout) {
        // SAFETY: see the impl.
        unsafe { mi::mi_free(ptr.cast::<c_void>()) }
    }

    #[inline]
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let ptr = ptr.cast::<c_void>();
        // SAFETY: see the impl.
        unsafe {
            if plain_call_aligns(layout) {
                mi::mi_realloc(ptr, new_size).cast()
            } else {
                mi::mi_realloc_aligned(ptr, new_size, layout.align()).cast()
            }
        }
    }
}

/// A block for `layout` from the plain call when every block has its alignment, else from the
/// aligned one.
///
/// # Safety
/// As `GlobalAlloc::alloc`: `layout` has a non-zero size.
#[inline(always)]
unsafe fn block(
    layout: Layout,
    plain: unsafe extern "C" fn(usize) -> *mut c_void,
    aligned: unsafe extern "C" fn(usize, usize) -> *mut c_void,
) -> *mut u8 {
    // SAFETY: both are mimalloc's allocation calls, given the layout's size (and alignment).
    unsafe {
        if plain_call_aligns(layout) {
            plain(layout.size()).cast()
        } else {
            aligned(layout.size(), layout.align()).cast()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Blocks of every size up to 64 KiB and every alignment up to 4 KiB come back aligned,
    /// zeroed when asked, and keep their bytes when resized (across the 8-byte boundary of
    /// the plain and aligned calls both ways).
    #[test]
    fn blocks_are_aligned_zeroed_and_resized_as_asked() {
        let a = MiMalloc;
        for align in [1, 2, 4, 8, 16, 32, 64, 4096] {
            for size in (1..=4096).step_by(7).chain([8192, 65536]) {
                let Ok(layout) = Layout::from_size_align(size, align) else {
                    panic!("layout {size} {align}");
                };
                // SAFETY: a non-zero size; each block is freed once with its own layout.
                unsafe {
                    let p = a.alloc_zeroed(layout);
                    assert!(!p.is_null());
                    assert_eq!(p as usize % align, 0, "size {size}, align {align}");
                    assert!(std::slice::from_raw_parts(p, size).iter().all(|&b| b == 0));
                    p.write_bytes(0xA5, size);
                    let grown = a.realloc(p, layout, size * 2);
                    assert!(!grown.is_null());
                    assert_eq!(grown as usize % align, 0, "resized {size}, align {align}");
                    assert!(std::slice::from_raw_parts(grown, size)
                        .iter()
                        .all(|&b| b == 0xA5));
                    let Ok(big) = Layout::from_size_align(size * 2, align) else {
                        panic!("layout");
                    };
                    a.dealloc(grown, big);
                    let q = a.alloc(layout);
                    assert_eq!(q as usize % align, 0);
                    a.dealloc(q, layout);
                }
            }
        }
    }
}
