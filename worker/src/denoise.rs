//! Denoising with Intel Open Image Denoise (OIDN), the field's standard denoiser, behind the
//! `denoise` cargo feature (the library is not part of every build: `pip install pyoidn` ships
//! it; build with `OIDN_DIR=<site-packages>/pyoidn/oidn`, run with its `lib` on the library
//! path).
//!
//! The input is the merged colour with the albedo and normal AOVs as auxiliary images (OIDN's
//! "RT" filter, HDR). Our AOVs are box-filtered sample means, noisy wherever the first hit
//! varies inside a pixel (edges, glass, depth of field, motion blur), so for the final frame we
//! do what OIDN's documentation recommends for the highest quality: prefilter the albedo and
//! the normal with RT filters of their own (their inputs only), then denoise the colour with the
//! prefiltered images and `cleanAux` set.
//!
//! Determinism: the device is always OIDN's CPU device (never "the fastest available", which
//! would be a GPU on some machines and give other bits). Two runs on one machine give the same
//! bits (tested); OIDN picks its kernels by instruction set (e.g. AVX2 or AVX-512), so workers
//! of different CPU generations may differ in the last bits of the denoised layer (never of the
//! noisy one).

use pathfarm_common::film::ImageLayers;
use pathfarm_common::protocol::DenoiseInput;

/// True if this binary can denoise (built with the `denoise` feature).
pub const AVAILABLE: bool = cfg!(feature = "denoise");

/// The denoised colour of `img` (same size, linear RGB): [`denoise_input`] of
/// [`DenoiseInput::of`] the image, as the farm's denoise steps do.
pub fn denoise(img: &ImageLayers) -> anyhow::Result<Vec<[f32; 3]>> {
    denoise_input(&DenoiseInput::of(img))
}

/// The denoised colour of a frame's colour, albedo and normal (same size, linear RGB): albedo
/// and normal prefiltered, then the colour with the clean auxiliary images. Deterministic for a
/// given input, OIDN build and CPU.
#[cfg(feature = "denoise")]
pub fn denoise_input(img: &DenoiseInput) -> anyhow::Result<Vec<[f32; 3]>> {
    let (w, h) = (img.width as usize, img.height as usize);
    let flat = |v: &[[f32; 3]]| v.iter().flatten().copied().collect::<Vec<f32>>();
    let (color, albedo, normal) = (flat(&img.color), flat(&img.albedo), flat(&img.normal));
    anyhow::ensure!(
        color.len() == w * h * 3 && albedo.len() == color.len() && normal.len() == color.len(),
        "image layers do not match the image size {w} x {h}"
    );
    let device = ffi::Device::cpu()?;
    let mut albedo_clean = vec![0.0f32; color.len()];
    device.rt_filter(&[("albedo", &albedo)], &mut albedo_clean, w, h, &[])?;
    let mut normal_clean = vec![0.0f32; color.len()];
    device.rt_filter(&[("normal", &normal)], &mut normal_clean, w, h, &[])?;
    let mut out = vec![0.0f32; color.len()];
    device.rt_filter(
        &[("color", &color), ("albedo", &albedo_clean), ("normal", &normal_clean)],
        &mut out,
        w,
        h,
        &[("hdr", true), ("srgb", false), ("cleanAux", true)],
    )?;
    Ok(out.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect())
}

/// The few OIDN calls we need beyond the `oidn` crate's wrapper, which always binds a `color`
/// input and so cannot run the albedo-only and normal-only prefilters. Every pointer handed to
/// OIDN is a live slice of `w * h * 3` floats (checked) that outlives the synchronous execute.
#[cfg(feature = "denoise")]
#[allow(unsafe_code)]
mod ffi {
    use oidn::sys::*;
    use std::ffi::{CStr, CString};

    pub struct Device(OIDNDevice);

    impl Drop for Device {
        fn drop(&mut self) {
            // SAFETY: the handle came from oidnNewDevice and is released once.
            unsafe { oidnReleaseDevice(self.0) }
        }
    }

    struct Filter(OIDNFilter);

    impl Drop for Filter {
        fn drop(&mut self) {
            // SAFETY: the handle came from oidnNewFilter and is released once.
            unsafe { oidnReleaseFilter(self.0) }
        }
    }

    fn c(name: &str) -> CString {
        CString::new(name).unwrap_or_default()
    }

    impl Device {
        /// OIDN's CPU device, committed.
        pub fn cpu() -> anyhow::Result<Self> {
            // SAFETY: plain constructor calls; a null handle is checked.
            let handle = unsafe { oidnNewDevice(OIDNDeviceType_OIDN_DEVICE_TYPE_CPU) };
            anyhow::ensure!(!handle.is_null(), "OIDN: no CPU device (is the library's CPU module installed?)");
            let device = Device(handle);
            // SAFETY: a valid device handle.
            unsafe { oidnCommitDevice(device.0) };
            device.check()?;
            Ok(device)
        }

        fn check(&self) -> anyhow::Result<()> {
            let mut message: *const std::os::raw::c_char = std::ptr::null();
            // SAFETY: a valid device; OIDN sets `message` to a string it owns (or leaves it null).
            let code = unsafe { oidnGetDeviceError(self.0, &mut message) };
            if code == OIDNError_OIDN_ERROR_NONE {
                return Ok(());
            }
            let text = if message.is_null() {
                String::new()
            } else {
                // SAFETY: a NUL-terminated string owned by OIDN, valid until the next call.
                unsafe { CStr::from_ptr(message) }.to_string_lossy().into_owned()
            };
            Err(anyhow::anyhow!("OIDN error {code}: {text}"))
        }

        /// Runs an "RT" filter with the named FLOAT3 inputs into `output`.
        pub fn rt_filter(
            &self,
            inputs: &[(&str, &[f32])],
            output: &mut [f32],
            w: usize,
            h: usize,
            flags: &[(&str, bool)],
        ) -> anyhow::Result<()> {
            let n = w * h * 3;
            anyhow::ensure!(output.len() == n && inputs.iter().all(|(_, v)| v.len() == n), "OIDN: image sizes differ");
            // SAFETY: a valid device; the filter is released by its Drop.
            let filter = Filter(unsafe { oidnNewFilter(self.0, c("RT").as_ptr()) });
            anyhow::ensure!(!filter.0.is_null(), "OIDN: no RT filter");
            let image = |name: &str, ptr: *mut std::ffi::c_void| {
                // SAFETY: `ptr` points at `n` floats = `w * h` packed FLOAT3 pixels (checked
                // above) that live until this function returns, after the synchronous execute.
                // OIDN only reads inputs.
                unsafe {
                    oidnSetSharedFilterImage(
                        filter.0,
                        c(name).as_ptr(),
                        ptr,
                        OIDNFormat_OIDN_FORMAT_FLOAT3,
                        w,
                        h,
                        0,
                        0,
                        0,
                    )
                }
            };
            for (name, values) in inputs {
                image(name, values.as_ptr().cast_mut().cast());
            }
            image("output", output.as_mut_ptr().cast());
            for (name, value) in flags {
                // SAFETY: a valid filter and a NUL-terminated name.
                unsafe { oidnSetFilterBool(filter.0, c(name).as_ptr(), *value) };
            }
            // SAFETY: a valid, fully configured filter; execution is synchronous.
            unsafe {
                oidnCommitFilter(filter.0);
                oidnExecuteFilter(filter.0);
            }
            self.check()
        }
    }
}

const NOT_AVAILABLE: &str = "this binary cannot denoise: build it with `--features pathfarm-worker/denoise` and \
     OIDN_DIR set (pip install pyoidn; OIDN_DIR=<site-packages>/pyoidn/oidn)";

/// An error saying how to get a denoising build, unless this is one.
pub fn ensure_available() -> anyhow::Result<()> {
    if AVAILABLE { Ok(()) } else { Err(anyhow::anyhow!(NOT_AVAILABLE)) }
}

/// Without the `denoise` feature: the error of [`ensure_available`].
#[cfg(not(feature = "denoise"))]
pub fn denoise_input(_img: &DenoiseInput) -> anyhow::Result<Vec<[f32; 3]>> {
    Err(anyhow::anyhow!(NOT_AVAILABLE))
}
