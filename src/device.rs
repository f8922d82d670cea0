//! What this process runs on: the libtorch it loaded, its CUDA backend, the GPUs and the CPU
//! kernels (`calibconv info`, and the `device` field of experiments).
//!
//! # The CUDA backend
//! libtorch's CUDA backend lives in `libtorch_cuda.so` and registers itself when that library is
//! loaded. Nothing in the crate calls into it directly, so `build.rs` links it with
//! `--no-as-needed` wherever the libtorch in use has it; [`RuntimeInfo::cuda_backend_linked`]
//! reads the process's own mappings (`/proc/self/maps`) to say whether it really was loaded
//! (the test `tests/integration/build_links.rs` checks the release binary's `NEEDED` list).
//!
//! # GPU names and library versions
//! tch exposes availability and counts, not names or versions. Those come from the C APIs of
//! the libraries libtorch already loaded: the CUDA driver (`libcuda.so.1`: `cuDeviceGetName`,
//! `cuDeviceTotalMem_v2`, `cuDriverGetVersion`), the CUDA runtime (`cudaRuntimeGetVersion`) and
//! cuDNN (`cudnnGetVersion`), looked up with `dlopen`/`dlsym`. Where a library is absent the
//! field is `None`: nothing is loaded that libtorch did not load, except the driver, which the
//! CUDA runtime loads itself as soon as CUDA is used.

use std::ffi::{c_char, c_int, c_uint, CStr, CString};
use std::path::PathBuf;

use serde::Serialize;
use tch::Device;

use crate::error::{Error, Result};
use crate::ops::{self, NativeSetting};

/// One CUDA device as the driver names it.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct CudaDevice {
    /// The device ordinal (`cuda:N`).
    pub index: usize,
    /// The driver's name (`NVIDIA H200`), if the driver answered.
    pub name: Option<String>,
    /// Total memory in GiB, if the driver answered.
    pub memory_gib: Option<f64>,
}

/// What this process runs on (`calibconv info`; `--json` prints this struct).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct RuntimeInfo {
    pub calibconv_version: String,
    /// The torch release the build checked (`build.rs`, from the venv's `torch/version.py`).
    pub libtorch_version: String,
    /// The folder `libtorch_cpu.so` was loaded from (this process's mappings).
    pub libtorch_dir: Option<PathBuf>,
    /// The tch release compiled in (from `Cargo.lock`).
    pub tch_version: String,
    /// Whether the build linked `libtorch_cuda.so` (it had one to link).
    pub cuda_backend_built: bool,
    /// Whether `libtorch_cuda.so` is loaded in this process.
    pub cuda_backend_linked: bool,
    pub cuda_available: bool,
    pub cuda_devices: Vec<CudaDevice>,
    /// `cuDriverGetVersion`, e.g. 13000 for CUDA 13.0.
    pub cuda_driver_version: Option<i32>,
    /// `cudaRuntimeGetVersion` of the runtime libtorch loaded.
    pub cuda_runtime_version: Option<i32>,
    pub cudnn_available: bool,
    /// `cudnnGetVersion`, e.g. 91002 for 9.10.2.
    pub cudnn_version: Option<usize>,
    /// Whether the native CPU kernels were compiled in (`build.rs`).
    pub native_cpu_kernels: bool,
    /// The instruction-set level of the few-output-channel kernels (`Avx512`, `Avx2`, `None`).
    pub small_kernel_isa: String,
    /// libtorch's intra-op CPU threads.
    pub threads: i32,
    /// libtorch's inter-op CPU threads.
    pub interop_threads: i32,
}

impl RuntimeInfo {
    /// Reads everything from this process.
    pub fn read() -> Self {
        let cuda_available = tch::Cuda::is_available();
        let count = if cuda_available {
            usize::try_from(tch::Cuda::device_count()).unwrap_or(0)
        } else {
            0
        };
        let driver = Driver::load();
        let cuda_devices = (0..count)
            .map(|index| CudaDevice {
                index,
                name: driver.as_ref().and_then(|d| d.name(index)),
                memory_gib: driver.as_ref().and_then(|d| d.memory_gib(index)),
            })
            .collect();
        Self {
            calibconv_version: env!("CARGO_PKG_VERSION").into(),
            libtorch_version: env!("CALIBCONV_LIBTORCH_VERSION").into(),
            libtorch_dir: loaded_library("libtorch_cpu.so")
                .and_then(|p| p.parent().map(Into::into)),
            tch_version: env!("CALIBCONV_TCH_VERSION").into(),
            cuda_backend_built: env!("CALIBCONV_CUDA_LINKED") == "1",
            cuda_backend_linked: loaded_library("libtorch_cuda.so").is_some(),
            cuda_available,
            cuda_devices,
            cuda_driver_version: driver.as_ref().and_then(Driver::version),
            cuda_runtime_version: loaded_symbol::<VersionFn>(
                &["libcudart.so.13", "libcudart.so.12"],
                "cudaRuntimeGetVersion",
            )
            .and_then(|f| out_int(|v| unsafe { f(v) })),
            cudnn_available: cuda_available && tch::Cuda::cudnn_is_available(),
            cudnn_version: loaded_symbol::<CudnnVersionFn>(
                &["libcudnn.so.9", "libcudnn.so.8"],
                "cudnnGetVersion",
            )
            .map(|f| unsafe { f() }),
            native_cpu_kernels: ops::native_available(),
            small_kernel_isa: format!("{:?}", ops::SmallKernelIsa::current()),
            threads: tch::get_num_threads(),
            interop_threads: tch::get_num_interop_threads(),
        }
    }

    /// The report `calibconv info` prints, one `key: value` line each.
    pub fn lines(&self) -> Vec<String> {
        let opt = |v: Option<String>| v.unwrap_or_else(|| "unknown".into());
        let yes = |b: bool| if b { "yes" } else { "no" }.to_string();
        let mut out = vec![
            format!("calibconv: {}", self.calibconv_version),
            format!("libtorch: {}", self.libtorch_version),
            format!(
                "libtorch loaded from: {}",
                opt(self.libtorch_dir.as_ref().map(|p| p.display().to_string()))
            ),
            format!("tch: {}", self.tch_version),
            format!(
                "CUDA backend: {} (libtorch_cuda.so {})",
                if self.cuda_backend_linked {
                    "linked"
                } else {
                    "not linked"
                },
                if self.cuda_backend_built {
                    "in the build"
                } else {
                    "absent from the build's libtorch"
                }
            ),
            format!("CUDA available: {}", yes(self.cuda_available)),
            format!("CUDA devices: {}", self.cuda_devices.len()),
        ];
        for d in &self.cuda_devices {
            out.push(format!(
                "  cuda:{}: {} ({})",
                d.index,
                opt(d.name.clone()),
                opt(d.memory_gib.map(|g| format!("{g:.1} GiB")))
            ));
        }
        out.extend([
            format!(
                "CUDA driver: {}",
                opt(self.cuda_driver_version.map(cuda_version))
            ),
            format!(
                "CUDA runtime: {}",
                opt(self.cuda_runtime_version.map(cuda_version))
            ),
            format!(
                "cuDNN: {} (version {})",
                if self.cudnn_available {
                    "available"
                } else {
                    "not available"
                },
                opt(self.cudnn_version.map(|v| v.to_string()))
            ),
            format!("native CPU kernels: {}", yes(self.native_cpu_kernels)),
            format!("few-output-channel kernels: {}", self.small_kernel_isa),
            format!(
                "CPU threads: {} (inter-op {})",
                self.threads, self.interop_threads
            ),
        ]);
        out
    }
}

/// `cpu` or `cuda:N`, as a `device` field writes it.
pub fn describe(device: Device) -> String {
    match device {
        Device::Cuda(n) => format!("cuda:{n}"),
        Device::Cpu => "cpu".into(),
        other => format!("{other:?}").to_lowercase(),
    }
}

/// `12080` as `12.8`.
fn cuda_version(v: i32) -> String {
    format!("{}.{}", v / 1000, (v % 1000) / 10)
}

/// `auto` | `cpu` | `cuda` | `cuda:N`, as written; `auto` is `cuda:0` where CUDA is available.
/// Syntax only: [`resolve`] also checks that the device exists.
pub fn parse(s: &str) -> Result<Device> {
    match s {
        "auto" => Ok(Device::cuda_if_available()),
        "cpu" => Ok(Device::Cpu),
        "cuda" => Ok(Device::Cuda(0)),
        other => other
            .strip_prefix("cuda:")
            .and_then(|n| n.parse::<usize>().ok())
            .map(Device::Cuda)
            .ok_or_else(|| {
                Error::InvalidArgument(format!(
                    "unknown device `{other}` (expected auto, cpu, cuda or cuda:N)"
                ))
            }),
    }
}

/// The device a `device` field names (`auto`, `cpu`, `cuda`, `cuda:N`), checked against this
/// process: `auto` takes `cuda:0` where CUDA is available, else the CPU; `cuda` and `cuda:N`
/// where CUDA is not available (or N is past the last device) are an error that says why
/// (`file` and `field` name where the value came from).
pub fn resolve(spec: &str, file: &std::path::Path, field: &str) -> Result<Device> {
    let device = parse(spec).map_err(|e| config_error(file, field, e.to_string()))?;
    if let Device::Cuda(n) = device {
        if !tch::Cuda::is_available() {
            let why = if loaded_library("libtorch_cuda.so").is_none() {
                "this calibconv's libtorch has no CUDA backend (libtorch_cuda.so is not loaded)"
            } else {
                "libtorch's CUDA backend finds no GPU (driver or device missing)"
            };
            return Err(config_error(
                file,
                field,
                format!(
                    "`{spec}` asks for CUDA, but {why}; use \"auto\" or \"cpu\", and see `calibconv info`"
                ),
            ));
        }
        let count = usize::try_from(tch::Cuda::device_count()).unwrap_or(0);
        if n >= count {
            return Err(config_error(
                file,
                field,
                format!(
                    "`{spec}`: this machine has {count} CUDA device(s) (cuda:0..cuda:{})",
                    count.saturating_sub(1)
                ),
            ));
        }
    }
    Ok(device)
}

fn config_error(file: &std::path::Path, field: &str, message: String) -> Error {
    Error::Config {
        path: file.to_path_buf(),
        field: field.into(),
        message,
    }
}

/// Device memory in use on the current CUDA context in bytes (`total - free` from the driver's
/// `cuMemGetInfo_v2`: every process's allocations on that GPU, libtorch's caching allocator's
/// reserve included), where the driver answers (a context must exist: call after CUDA work).
pub fn cuda_memory_in_use() -> Option<u64> {
    let info: MemInfoFn = symbol_of("libcuda.so.1", "cuMemGetInfo_v2", libc::RTLD_NOW)?;
    let (mut free, mut total) = (0usize, 0usize);
    // SAFETY: two size_t out-parameters, the documented signature.
    let rc = unsafe { info(&mut free, &mut total) };
    (rc == 0).then(|| (total - free) as u64)
}

/// The path of a loaded shared library whose file name is `name` (from `/proc/self/maps`).
pub fn loaded_library(name: &str) -> Option<PathBuf> {
    let maps = std::fs::read_to_string("/proc/self/maps").ok()?;
    maps.lines()
        .filter_map(|l| l.split_whitespace().nth(5))
        .map(PathBuf::from)
        .find(|p| p.file_name().is_some_and(|f| f == name))
}

type VersionFn = unsafe extern "C" fn(*mut c_int) -> c_int;
type CudnnVersionFn = unsafe extern "C" fn() -> usize;
type InitFn = unsafe extern "C" fn(c_uint) -> c_int;
type DeviceGetFn = unsafe extern "C" fn(*mut c_int, c_int) -> c_int;
type NameFn = unsafe extern "C" fn(*mut c_char, c_int, c_int) -> c_int;
type TotalMemFn = unsafe extern "C" fn(*mut usize, c_int) -> c_int;
type MemInfoFn = unsafe extern "C" fn(*mut usize, *mut usize) -> c_int;

/// Calls `f` with an out-parameter; its value where `f` returned 0 (success).
fn out_int(f: impl FnOnce(*mut c_int) -> c_int) -> Option<i32> {
    let mut v: c_int = 0;
    (f(&mut v) == 0).then_some(v)
}

/// A symbol of a library this process already loaded (by any of `sonames`).
fn loaded_symbol<F: Copy>(sonames: &[&str], symbol: &str) -> Option<F> {
    sonames
        .iter()
        .find_map(|s| symbol_of(s, symbol, libc::RTLD_NOW | libc::RTLD_NOLOAD))
}

/// `dlsym(dlopen(soname, flags), symbol)` as a function pointer of type `F`.
fn symbol_of<F: Copy>(soname: &str, symbol: &str, flags: c_int) -> Option<F> {
    assert_eq!(
        std::mem::size_of::<F>(),
        std::mem::size_of::<*mut libc::c_void>()
    );
    let soname = CString::new(soname).ok()?;
    let symbol = CString::new(symbol).ok()?;
    // SAFETY: dlopen/dlsym with valid C strings; the handle is never closed (the library stays
    // loaded for the process, as libtorch's own libraries do), and F is a function pointer type
    // of the symbol's C signature (checked size above).
    unsafe {
        let handle = libc::dlopen(soname.as_ptr(), flags);
        if handle.is_null() {
            return None;
        }
        let sym = libc::dlsym(handle, symbol.as_ptr());
        (!sym.is_null()).then(|| std::mem::transmute_copy::<*mut libc::c_void, F>(&sym))
    }
}

/// The CUDA driver API's few calls used here.
struct Driver {
    device_get: DeviceGetFn,
    name: NameFn,
    total_mem: TotalMemFn,
    version: VersionFn,
}

impl Driver {
    /// The driver, initialised, where `libcuda.so.1` exists and `cuInit` succeeds.
    fn load() -> Option<Self> {
        let flags = libc::RTLD_NOW | libc::RTLD_GLOBAL;
        let init: InitFn = symbol_of("libcuda.so.1", "cuInit", flags)?;
        // SAFETY: cuInit(0) is the documented first call; the others are looked up by name with
        // their documented signatures.
        unsafe {
            if init(0) != 0 {
                return None;
            }
            Some(Self {
                device_get: symbol_of("libcuda.so.1", "cuDeviceGet", flags)?,
                name: symbol_of("libcuda.so.1", "cuDeviceGetName", flags)?,
                total_mem: symbol_of("libcuda.so.1", "cuDeviceTotalMem_v2", flags)?,
                version: symbol_of("libcuda.so.1", "cuDriverGetVersion", flags)?,
            })
        }
    }

    fn handle(&self, index: usize) -> Option<c_int> {
        let ordinal = c_int::try_from(index).ok()?;
        out_int(|d| unsafe { (self.device_get)(d, ordinal) })
    }

    fn name(&self, index: usize) -> Option<String> {
        let dev = self.handle(index)?;
        let mut buf = [0 as c_char; 256];
        // SAFETY: the buffer's length is passed; the driver writes a NUL-terminated name.
        let rc = unsafe { (self.name)(buf.as_mut_ptr(), buf.len() as c_int, dev) };
        (rc == 0).then(|| {
            unsafe { CStr::from_ptr(buf.as_ptr()) }
                .to_string_lossy()
                .into_owned()
        })
    }

    fn memory_gib(&self, index: usize) -> Option<f64> {
        let dev = self.handle(index)?;
        let mut bytes = 0usize;
        // SAFETY: one out-parameter of size_t.
        let rc = unsafe { (self.total_mem)(&mut bytes, dev) };
        (rc == 0).then(|| bytes as f64 / f64::from(1u32 << 30))
    }

    fn version(&self) -> Option<i32> {
        out_int(|v| unsafe { (self.version)(v) })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_this_process() {
        let info = RuntimeInfo::read();
        // The test executable itself is linked to libtorch: its folder is found.
        let dir = info
            .libtorch_dir
            .clone()
            .expect("libtorch_cpu.so is mapped");
        assert!(dir.join("libtorch_cpu.so").is_file(), "{}", dir.display());
        // What the build linked is loaded.
        assert_eq!(info.cuda_backend_built, info.cuda_backend_linked);
        assert_eq!(info.cuda_available, !info.cuda_devices.is_empty());
        assert!(info.threads >= 1);
        assert!(info.lines().iter().any(|l| l.starts_with("CUDA backend: ")));
    }

    #[test]
    fn cuda_where_unavailable_names_file_and_field() {
        let file = std::path::Path::new("/x/exp.toml");
        assert_eq!(resolve("cpu", file, "device").unwrap(), Device::Cpu);
        let auto = resolve("auto", file, "device").unwrap();
        assert_eq!(auto.is_cuda(), tch::Cuda::is_available());
        let bad = resolve("gpu", file, "device").unwrap_err().to_string();
        assert!(bad.starts_with("/x/exp.toml: `device`:"), "{bad}");
        if !tch::Cuda::is_available() {
            let e = resolve("cuda", file, "device").unwrap_err().to_string();
            assert!(e.starts_with("/x/exp.toml: `device`:"), "{e}");
            assert!(e.contains("asks for CUDA"), "{e}");
        } else {
            let e = resolve("cuda:4096", file, "device")
                .unwrap_err()
                .to_string();
            assert!(e.contains("CUDA device(s)"), "{e}");
        }
    }

    #[test]
    fn cuda_versions_read_as_major_minor() {
        assert_eq!(cuda_version(13000), "13.0");
        assert_eq!(cuda_version(12080), "12.8");
    }
}
