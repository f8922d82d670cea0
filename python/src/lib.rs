//! `calibconv._native`: the Python binding (PyO3) of `calibconv-geometry`, no libtorch inside.
//!
//! - [`Camera`]: a camera of any model, read from a camera file ([`Camera::load`]) or imported
//!   from another tool's calibration ([`Camera::import_`]); [`Camera::project`] and
//!   [`Camera::unproject`] map numpy `[N, 3]` rays to `[N, 2]` pixels and back, in Rust, one row
//!   at a time, NaN rows where the model has no answer (the crate's `None`).
//! - [`offsets`]: one layer's calibrated offsets as a float32 numpy `[2*kh*kw, H_out, W_out]`
//!   array, from the same `compute_offsets` as `calibconv offsets` (so bit-identical to it).
//!
//! - [`sampling_plan`]: a layer's sampling plan from its offsets (top-left corners, fractions,
//!   rows read) as numpy arrays, from the same `calibconv_geometry::plan` as the crate's
//!   `SamplingPlan` (so bit-identical to it), for the native kernels.
//! - [`native_sources`]: the native kernels' C++ sources (`src/ops/native`, embedded at build
//!   time: one source for the crate and the package), which `calibconv.torch` compiles against
//!   the installed torch.
//!
//! Conventions are the geometry crate's: pixels `[u, v]` = (column, row), top-left pixel centre
//! at `(0, 0)`; rays `[x, y, z]` (x right, y down, z forward); layer pairs `(y, x)`; the input
//! padding `(p_w, p_h)`, right and bottom.
//!
//! Errors: a missing file is `FileNotFoundError`, other I/O `OSError`, everything else
//! (a camera file's field, an import, a shape, a layer geometry, a feature map too small for the
//! field of view) `ValueError`, with the crate's message (file and field named).

use std::path::PathBuf;

use numpy::ndarray::{Array1, Array2, Array3};
use numpy::{AllowTypeChange, IntoPyArray, PyArray1, PyArray2, PyArray3, PyArrayLikeDyn};
use pyo3::exceptions::{PyFileNotFoundError, PyOSError, PyValueError};
use pyo3::prelude::*;

use calibconv_geometry::camera::import::{import_file, Format, ImportOptions, OpenCvModel};
use calibconv_geometry::camera::{self, CameraModel, PixelConvention};
use calibconv_geometry::kernel::{compute_offsets, InputFrame, LayerGeometry};
use calibconv_geometry::plan::PlanLayout;
use calibconv_geometry::Error;

/// The geometry crate's error as the Python exception that fits it.
fn py_err(e: Error) -> PyErr {
    match &e {
        Error::Io { source, .. } if source.kind() == std::io::ErrorKind::NotFound => {
            PyFileNotFoundError::new_err(e.to_string())
        }
        Error::Io { .. } => PyOSError::new_err(e.to_string()),
        _ => PyValueError::new_err(e.to_string()),
    }
}

/// A camera model (Kannala-Brandt, pinhole, radial-tangential, double sphere, unified, extended
/// unified, Scaramuzza, equirectangular) with its image size and field of view.
#[pyclass(name = "Camera", module = "calibconv", frozen)]
struct Camera {
    inner: camera::Camera,
}

/// A `[N, C]` float64 array from any array-like (lists, float32 arrays are converted), or a
/// `ValueError` naming `what` and the shape it got.
fn rows<'py>(
    arr: &'py PyArrayLikeDyn<'py, f64, AllowTypeChange>,
    what: &str,
    cols: usize,
) -> PyResult<numpy::ndarray::ArrayView2<'py, f64>> {
    let view = arr.as_array();
    let shape = view.shape().to_vec();
    if shape.len() != 2 || shape[1] != cols {
        return Err(PyValueError::new_err(format!(
            "{what} must have shape [N, {cols}], got {shape:?}"
        )));
    }
    view.into_dimensionality()
        .map_err(|e| PyValueError::new_err(format!("{what}: {e}")))
}

/// `f` of each row of the `[N, IN]` array `input` (checked by [`rows`], `what` in errors):
/// `[N, OUT]`, NaN rows where `f` is `None` (the body of `project` and `unproject`).
fn map_rows<'py, const IN: usize, const OUT: usize>(
    py: Python<'py>,
    input: &PyArrayLikeDyn<'_, f64, AllowTypeChange>,
    what: &str,
    f: impl Fn([f64; IN]) -> Option<[f64; OUT]>,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let input = rows(input, what, IN)?;
    let mut out = Array2::from_elem((input.nrows(), OUT), f64::NAN);
    for (r, mut o) in input.outer_iter().zip(out.outer_iter_mut()) {
        if let Some(v) = f(std::array::from_fn(|i| r[i])) {
            o.assign(&numpy::ndarray::ArrayView1::from(&v));
        }
    }
    Ok(out.into_pyarray(py))
}

#[pymethods]
impl Camera {
    /// Reads a camera file (TOML, see `data/cameras/`).
    ///
    /// Raises `FileNotFoundError` for a missing file and `ValueError` for an invalid one (the
    /// message names the file and the field).
    #[staticmethod]
    fn load(path: PathBuf) -> PyResult<Self> {
        let inner = camera::load(&path).map_err(py_err)?;
        Ok(Camera { inner })
    }

    /// Imports another tool's calibration: `tool` is `kalibr`, `opencv`, `basalt`, `colmap`,
    /// `ocamcalib`, `ros` or `orbslam3` (as `calibconv camera import --from`). `camera` picks one
    /// camera of a multi-camera file (Kalibr `camN`, Basalt `intrinsics[N]`, the N-th camera of a
    /// ROS `ost.txt`, ORB-SLAM3 0 or 1, COLMAP `CAMERA_ID`), `fov_deg`
    /// sets a fisheye's field of view (default: the angle spanned by the image width),
    /// `opencv_model` is `fisheye` or `standard` for OpenCV files that do not say.
    #[staticmethod]
    #[pyo3(signature = (tool, path, *, camera=None, fov_deg=None, opencv_model=None))]
    fn import_(
        tool: &str,
        path: PathBuf,
        camera: Option<usize>,
        fov_deg: Option<f64>,
        opencv_model: Option<&str>,
    ) -> PyResult<Self> {
        let format: Format = tool.parse().map_err(PyValueError::new_err)?;
        let opencv_model = opencv_model
            .map(|m| m.parse::<OpenCvModel>())
            .transpose()
            .map_err(PyValueError::new_err)?;
        let options = ImportOptions {
            camera,
            fov_deg,
            opencv_model,
        };
        let imported = import_file(format, &path, &options).map_err(py_err)?;
        Ok(Camera {
            inner: imported.camera,
        })
    }

    /// Image width in pixels.
    #[getter]
    fn width(&self) -> usize {
        self.inner.size()[0]
    }

    /// Image height in pixels.
    #[getter]
    fn height(&self) -> usize {
        self.inner.size()[1]
    }

    /// Full horizontal field of view in degrees.
    #[getter]
    fn fov_deg(&self) -> f64 {
        self.inner.fov().to_degrees()
    }

    /// The model's name in camera files (`model = "..."`).
    #[getter]
    fn model(&self) -> &'static str {
        self.inner.model_name()
    }

    /// The camera as a camera file (TOML text, `calibconv camera import`'s format).
    fn to_toml(&self) -> String {
        camera::to_toml(&self.inner, &[], None, None)
    }

    /// Pixels `[N, 2]` (`u`, `v`) of rays `[N, 3]` (any length > 0); NaN rows outside the
    /// model's domain.
    fn project<'py>(
        &self,
        py: Python<'py>,
        rays: PyArrayLikeDyn<'py, f64, AllowTypeChange>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        map_rows(py, &rays, "rays", |ray: [f64; 3]| self.inner.project(ray))
    }

    /// Unit rays `[N, 3]` of pixels `[N, 2]` (`u`, `v`); NaN rows where the model has no inverse.
    fn unproject<'py>(
        &self,
        py: Python<'py>,
        px: PyArrayLikeDyn<'py, f64, AllowTypeChange>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        map_rows(py, &px, "pixels", |px: [f64; 2]| self.inner.unproject(px))
    }

    fn __repr__(&self) -> String {
        let [w, h] = self.inner.size();
        format!(
            "Camera(model={:?}, width={w}, height={h}, fov_deg={})",
            self.inner.model_name(),
            self.inner.fov().to_degrees()
        )
    }
}

/// A camera argument: a [`Camera`] or the path of a camera file.
#[derive(FromPyObject)]
enum CameraArg<'py> {
    Camera(PyRef<'py, Camera>),
    Path(PathBuf),
}

/// An int or a pair of ints (`(y, x)`), each at least `min`, or a `ValueError` naming `name`.
fn pair(obj: &Bound<'_, PyAny>, name: &str, min: i64) -> PyResult<[usize; 2]> {
    let v: [i64; 2] = match obj.extract::<i64>() {
        Ok(n) => [n, n],
        Err(_) => obj
            .extract::<(i64, i64)>()
            .map(|(a, b)| [a, b])
            .map_err(|_| {
                PyValueError::new_err(format!(
                    "{name} must be an int or a pair of ints, got {obj}"
                ))
            })?,
    };
    if v.iter().any(|&n| n < min) {
        return Err(PyValueError::new_err(format!(
            "{name} must be >= {min}, got {v:?}"
        )));
    }
    Ok(v.map(|n| n as usize))
}

/// One layer's calibrated offsets, float32 `[2*kh*kw, H_out, W_out]` (torchvision's layout:
/// per tap, row-major, the pair `(dy, dx)`), for an input feature map `size = (H, W)`.
///
/// `kernel`, `stride`, `padding`, `dilation`: ints or `(y, x)` pairs as in `nn.Conv2d`;
/// `padding=None` is "same", `dilation * (kernel - 1) // 2`. `input_padding = (p_w, p_h)`: pixels
/// added right and bottom of the camera image to form the network input. `convention`:
/// `half-pixel` or `paper` (how intrinsics scale to the feature map). Equal bit for bit to
/// `calibconv offsets --camera F --size HxW --kernel K --stride S --dilation D
/// --conv-padding P --padding PW,PH --convention C`.
#[pyfunction]
#[pyo3(signature = (cam, size, kernel=None, stride=None, padding=None, dilation=None,
                    input_padding=(0, 0), convention="half-pixel"))]
#[allow(clippy::too_many_arguments)]
fn offsets<'py>(
    py: Python<'py>,
    cam: CameraArg<'py>,
    size: &Bound<'py, PyAny>,
    kernel: Option<&Bound<'py, PyAny>>,
    stride: Option<&Bound<'py, PyAny>>,
    padding: Option<&Bound<'py, PyAny>>,
    dilation: Option<&Bound<'py, PyAny>>,
    input_padding: (usize, usize),
    convention: &str,
) -> PyResult<Bound<'py, PyArray3<f32>>> {
    let loaded;
    let cam = match &cam {
        CameraArg::Camera(c) => &c.inner,
        CameraArg::Path(p) => {
            loaded = camera::load(p).map_err(py_err)?;
            &loaded
        }
    };
    let opt = |v: Option<&Bound<'py, PyAny>>, name: &str, default: usize, min: i64| match v {
        Some(v) => pair(v, name, min),
        None => Ok([default; 2]),
    };
    let input_size = pair(size, "size", 1)?;
    let kernel = opt(kernel, "kernel", 3, 1)?;
    let stride = opt(stride, "stride", 1, 1)?;
    let dilation = opt(dilation, "dilation", 1, 1)?;
    if kernel.iter().any(|k| k % 2 == 0) {
        return Err(PyValueError::new_err(format!(
            "kernel {kernel:?}: calibrated kernels need odd sizes"
        )));
    }
    let padding = match padding {
        Some(p) => pair(p, "padding", 0)?,
        None => [0, 1].map(|a| dilation[a] * (kernel[a] - 1) / 2),
    };
    let convention: PixelConvention = convention.parse().map_err(PyValueError::new_err)?;
    let geometry = LayerGeometry {
        kernel,
        stride,
        padding,
        dilation,
    };
    let frame = InputFrame {
        padding: [input_padding.0, input_padding.1],
        convention,
    };
    let off = py
        .detach(|| compute_offsets(cam, input_size, &geometry, &frame))
        .map_err(py_err)?;
    let [c, ho, wo] = off.shape();
    let arr = Array3::from_shape_vec((c, ho, wo), off.data)
        .map_err(|e| PyValueError::new_err(format!("offsets: {e}")))?;
    Ok(arr.into_pyarray(py))
}

/// A layer's sampling plan for offsets `[2*kh*kw, H_out, W_out]` (shared by the batch, zeros
/// outside) on an input of `size = (H, W)`: `(top_left, frac, rows)`, int32 `[N]`, float64
/// `[2 N]` and int32 `[H_out, 2]` for `N = H_out * W_out * kh * kw` samples (pixel-major, then
/// tap): each sample's top-left bilinear corner in the input padded by one row above, two below
/// and a column on each side, its fractions `(ly, lx)`, and per output row the lowest and highest
/// input row read. The crate's `SamplingPlan` for the same offsets holds the same values (its
/// float32 fractions are these rounded). `kernel`, `stride`, `padding`, `dilation`: `(y, x)`
/// pairs as `nn.Conv2d`'s.
#[pyfunction]
#[pyo3(signature = (offsets, size, kernel, stride, padding, dilation))]
#[allow(clippy::type_complexity)]
fn sampling_plan<'py>(
    py: Python<'py>,
    offsets: PyArrayLikeDyn<'py, f64, AllowTypeChange>,
    size: (i64, i64),
    kernel: (i64, i64),
    stride: (i64, i64),
    padding: (i64, i64),
    dilation: (i64, i64),
) -> PyResult<(
    Bound<'py, PyArray1<i32>>,
    Bound<'py, PyArray1<f64>>,
    Bound<'py, PyArray2<i32>>,
)> {
    let arr = |(a, b): (i64, i64)| [a, b];
    let (input, kernel, stride, padding, dilation) = (
        arr(size),
        arr(kernel),
        arr(stride),
        arr(padding),
        arr(dilation),
    );
    if input
        .iter()
        .chain(&kernel)
        .chain(&stride)
        .chain(&dilation)
        .any(|&v| v < 1)
        || padding.iter().any(|&p| p < 0)
    {
        return Err(PyValueError::new_err(format!(
            "sampling_plan: size {input:?}, kernel {kernel:?}, stride {stride:?}, dilation \
             {dilation:?} must be >= 1 and padding {padding:?} >= 0"
        )));
    }
    let out = |a: usize| {
        (input[a] + 2 * padding[a] - dilation[a] * (kernel[a] - 1) - 1).div_euclid(stride[a]) + 1
    };
    let (ho, wo) = (out(0), out(1));
    let taps = kernel[0] * kernel[1];
    let view = offsets.as_array();
    let want = [2 * taps, ho, wo];
    if ho < 1 || wo < 1 || view.shape() != want.map(|v| v.max(0) as usize) {
        return Err(PyValueError::new_err(format!(
            "sampling_plan: offsets of shape {:?} do not fit a {}x{} kernel (stride {stride:?}, \
             padding {padding:?}, dilation {dilation:?}) on a {}x{} input: expected {want:?}",
            view.shape(),
            kernel[0],
            kernel[1],
            input[0],
            input[1]
        )));
    }
    let layout = PlanLayout {
        h: input[0],
        w: input[1],
        ho,
        wo,
        kernel,
        stride,
        padding,
        dilation,
        per_item: false,
        wrap: false,
    };
    let samples = layout.samples(1).ok_or_else(|| {
        PyValueError::new_err(format!(
            "sampling_plan: {ho}x{wo} x {taps} samples on a {}x{} input are too many for int32 \
             indices",
            input[0], input[1]
        ))
    })?;
    let off: Vec<f64> = view.iter().copied().collect();
    let (top_left, frac, rows) = py.detach(|| {
        let mut top_left = vec![0i32; samples];
        let mut frac = vec![0f64; 2 * samples];
        let rows = layout.fill(&off, &mut top_left, &mut frac);
        (top_left, frac, rows)
    });
    let rows = Array2::from_shape_vec((ho as usize, 2), rows.into_iter().flatten().collect())
        .map_err(|e| PyValueError::new_err(format!("sampling_plan: {e}")))?;
    Ok((
        Array1::from_vec(top_left).into_pyarray(py),
        Array1::from_vec(frac).into_pyarray(py),
        rows.into_pyarray(py),
    ))
}

/// `[(file, include_str!(src/ops/native/file))]` for the files named.
macro_rules! native_sources {
    ($($file:literal),* $(,)?) => {
        [$(($file, include_str!(concat!("../../src/ops/native/", $file)))),*]
    };
}
/// The native kernels' C++ sources, `(file name, text)`, embedded from `src/ops/native` when
/// this module is built: the files `build.rs` compiles into the crate, plus `torch_op.cpp`, their
/// registration as torch operators.
const NATIVE_SOURCES: [(&str, &str); 13] = native_sources!(
    "deform.cpp",
    "forward.cpp",
    "gather.cpp",
    "grad_input.cpp",
    "grad_weight.cpp",
    "layout.cpp",
    "padding.cpp",
    "small.cpp",
    "torch_op.cpp",
    "deform.h",
    "gather.h",
    "simd.h",
    "small_kernels.h",
);

/// The native kernels' C++ sources as `[(file name, text)]` (see [`NATIVE_SOURCES`]).
#[pyfunction]
fn native_sources() -> Vec<(&'static str, &'static str)> {
    NATIVE_SOURCES.to_vec()
}

/// The module: `Camera`, `offsets`, `sampling_plan`, `native_sources`, `MODELS` (the camera-file
/// model names), `__version__`.
#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<Camera>()?;
    m.add_function(wrap_pyfunction!(offsets, m)?)?;
    m.add_function(wrap_pyfunction!(sampling_plan, m)?)?;
    m.add_function(wrap_pyfunction!(native_sources, m)?)?;
    m.add("MODELS", camera::MODELS.to_vec())?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
