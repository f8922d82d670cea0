//! Platform probes of the benchmark: the CPU's name, the load average, the process CPU time,
//! resident memory (`/proc/self/status`, `/proc/self/clear_refs`) and glibc's mmap threshold. Real
//! on Linux only; elsewhere each one reports `None` or does nothing.

/// The CPU's name (`/proc/cpuinfo`'s first `model name`), where the platform has it: the
/// figures of one CPU do not carry over to another (the kernels' choices differ by CPU).
#[cfg(target_os = "linux")]
pub(super) fn cpu_model() -> Option<String> {
    let text = std::fs::read_to_string("/proc/cpuinfo").ok()?;
    text.lines()
        .find_map(|l| l.strip_prefix("model name")?.split_once(':'))
        .map(|(_, name)| name.trim().to_string())
}

#[cfg(not(target_os = "linux"))]
pub(super) fn cpu_model() -> Option<String> {
    None
}

/// `/proc/loadavg`'s three load averages, where the platform has them.
#[cfg(target_os = "linux")]
pub(super) fn load_average() -> Option<[f64; 3]> {
    let text = std::fs::read_to_string("/proc/loadavg").ok()?;
    let v: Vec<f64> = text
        .split_whitespace()
        .take(3)
        .map(|x| x.parse().ok())
        .collect::<Option<_>>()?;
    v.try_into().ok()
}

#[cfg(not(target_os = "linux"))]
pub(super) fn load_average() -> Option<[f64; 3]> {
    None
}

/// CPU time of the process (all threads, user + system) in seconds, where the platform has it.
pub(super) fn cpu_seconds() -> Option<f64> {
    #[cfg(target_os = "linux")]
    {
        #[repr(C)]
        struct Timespec {
            sec: i64,
            nsec: i64,
        }
        extern "C" {
            fn clock_gettime(clock: std::ffi::c_int, ts: *mut Timespec) -> std::ffi::c_int;
        }
        const CLOCK_PROCESS_CPUTIME_ID: std::ffi::c_int = 2;
        let mut ts = Timespec { sec: 0, nsec: 0 };
        // SAFETY: clock_gettime writes one timespec (two 64-bit fields on 64-bit Linux) to `ts`.
        let rc = unsafe { clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &mut ts) };
        (rc == 0).then_some(ts.sec as f64 + ts.nsec as f64 * 1e-9)
    }
    #[cfg(not(target_os = "linux"))]
    None
}

/// Reads a `kB` field of `/proc/self/status`.
#[cfg(target_os = "linux")]
fn status_kib(field: &str) -> Option<f64> {
    let text = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = text.lines().find(|l| l.starts_with(field))?;
    line[field.len()..]
        .trim()
        .trim_end_matches("kB")
        .trim()
        .parse()
        .ok()
}

/// Peak resident memory (MiB) that `f` adds: `VmHWM` after minus `VmRSS` before, with the
/// high-water mark reset first. `None` where `/proc` does not support it.
#[cfg(target_os = "linux")]
pub(super) fn peak_mib(f: &mut dyn FnMut()) -> Option<f64> {
    std::fs::write("/proc/self/clear_refs", "5").ok()?;
    let before = status_kib("VmRSS:")?;
    f();
    let peak = status_kib("VmHWM:")?;
    Some((peak - before).max(0.0) / 1024.0)
}

#[cfg(not(target_os = "linux"))]
pub(super) fn peak_mib(_f: &mut dyn FnMut()) -> Option<f64> {
    None
}

/// Pins glibc's mmap threshold so large freed blocks are unmapped at once (see the module docs).
pub(super) fn pin_malloc_threshold() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        extern "C" {
            fn mallopt(param: std::ffi::c_int, value: std::ffi::c_int) -> std::ffi::c_int;
        }
        const M_MMAP_THRESHOLD: std::ffi::c_int = -3;
        // SAFETY: mallopt only changes allocator tuning; called before the benchmark allocates.
        unsafe {
            mallopt(M_MMAP_THRESHOLD, 256 * 1024);
        }
    }
}
