//! Denoising with Intel Open Image Denoise (OIDN), the field's standard denoiser, behind the
//! `denoise` cargo feature (the library is not part of every build: `pip install pyoidn` ships
//! it; build with `OIDN_DIR=<site-packages>/pyoidn/oidn`, run with its `lib` on the library
//! path). The input is the merged colour with the albedo and normal AOVs as auxiliary images
//! (OIDN's "RT" filter, HDR, high quality); the AOVs are noisy like the colour (box-filtered
//! sample means), which OIDN expects unless told `cleanAux`.

use pathfarm_common::film::ImageLayers;

/// True if this binary can denoise (built with the `denoise` feature).
pub const AVAILABLE: bool = cfg!(feature = "denoise");

/// The denoised colour of `img` (same size, linear RGB). Deterministic for a given image, OIDN
/// build and CPU.
#[cfg(feature = "denoise")]
pub fn denoise(img: &ImageLayers) -> anyhow::Result<Vec<[f32; 3]>> {
    let oidn_error = |e: oidn::Error| anyhow::anyhow!("OIDN: {e:?}");
    let (w, h) = (img.width as usize, img.height as usize);
    let flat = |v: &[[f32; 3]]| v.iter().flatten().copied().collect::<Vec<f32>>();
    let (color, albedo, normal) = (flat(&img.rgb), flat(&img.albedo), flat(&img.normal));
    anyhow::ensure!(color.len() == w * h * 3 && albedo.len() == color.len() && normal.len() == color.len());
    let device = oidn::Device::new().map_err(oidn_error)?;
    let mut out = vec![0.0f32; color.len()];
    oidn::RayTracing::try_new(&device)
        .map_err(oidn_error)?
        .hdr(true)
        .srgb(false)
        .image_dimensions(w, h)
        .albedo_normal(&albedo, &normal)
        .filter(&color, &mut out)
        .map_err(oidn_error)?;
    device.get_error().map_err(oidn_error)?;
    Ok(out.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect())
}

const NOT_AVAILABLE: &str = "this binary cannot denoise: build it with `--features pathfarm-worker/denoise` and \
     OIDN_DIR set (pip install pyoidn; OIDN_DIR=<site-packages>/pyoidn/oidn)";

/// An error saying how to get a denoising build, unless this is one.
pub fn ensure_available() -> anyhow::Result<()> {
    if AVAILABLE { Ok(()) } else { Err(anyhow::anyhow!(NOT_AVAILABLE)) }
}

/// Without the `denoise` feature: the error of [`ensure_available`].
#[cfg(not(feature = "denoise"))]
pub fn denoise(_img: &ImageLayers) -> anyhow::Result<Vec<[f32; 3]>> {
    Err(anyhow::anyhow!(NOT_AVAILABLE))
}
