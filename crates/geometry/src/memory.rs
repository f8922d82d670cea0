//! Large fresh buffers (the offsets here, the sampling plans in `calibconv::ops`) backed by
//! transparent huge pages where the kernel offers them on request.
//!
//! A buffer of hundreds of MiB (the F195 pyramid's plans hold 287 MiB) is fresh anonymous memory
//! that faults in page by page as the parallel row tasks first write it: with 4 KiB pages that
//! was a fifth of the pyramid's CPU time in the kernel (page faults, then unmapping). Linux's
//! default `transparent_hugepage = madvise` gives 2 MiB pages only to memory that asks with
//! `madvise(MADV_HUGEPAGE)`; with `always` the call changes nothing, with `never` it is ignored.

/// Buffers smaller than this are left alone: a huge page needs an aligned 2 MiB of the buffer.
const MIN_BYTES: usize = 4 << 20;

/// Asks the kernel to back the not yet touched memory of `buf` with transparent huge pages
/// (Linux; elsewhere, and for buffers under 4 MiB, nothing). Call it before the first write; it
/// changes no value and failures are ignored (the memory then stays in small pages).
pub fn advise_huge_pages<T>(buf: &mut [T]) {
    let bytes = std::mem::size_of_val(buf);
    if bytes < MIN_BYTES {
        return;
    }
    #[cfg(target_os = "linux")]
    {
        // madvise needs a page-aligned start: the whole pages inside the buffer.
        const PAGE: usize = 4096;
        let start = buf.as_mut_ptr() as usize;
        let first = start.next_multiple_of(PAGE);
        let end = (start + bytes) / PAGE * PAGE;
        if end > first {
            // SAFETY: [first, end) lies inside `buf`, memory this process owns; MADV_HUGEPAGE
            // only changes how future faults are served, never the contents.
            unsafe {
                libc::madvise(first as *mut libc::c_void, end - first, libc::MADV_HUGEPAGE);
            }
        }
    }
}
