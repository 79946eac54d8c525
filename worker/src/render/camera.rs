//! Cameras: pinhole perspective and orthographic, from the scene's glTF cameras, or a default
//! perspective camera framing the scene bounds; a perspective camera may get a thin lens (the
//! job's `aperture_radius` and `focus_distance`: glTF cameras have no aperture).

use super::geometry::Ray;
use super::math::Real;
use super::sampler::Sampler;
use super::sampling::sample_uniform_disk_concentric;
use glam::{Affine3A, Mat4, UVec2, Vec2, Vec3, Vec3A};
use pathfarm_common::scene::{self, Projection};

#[derive(Clone, Copy, Debug)]
enum Kind {
    /// `tan(yfov / 2)` and the image aspect ratio.
    Perspective {
        tan_half_y: f32,
        aspect: f32,
    },
    Orthographic {
        xmag: f32,
        ymag: f32,
    },
}

/// A camera bound to an image size.
#[derive(Clone, Debug)]
pub struct Camera {
    world_from_camera: Affine3A,
    camera_from_world: Affine3A,
    kind: Kind,
    width: u32,
    height: u32,
    lens: Option<Lens>,
}

/// A thin lens (pbrt's `PerspectiveCamera` with `lensRadius > 0`): rays start on a disk of
/// `radius` around the camera position, perpendicular to the view axis, and all rays through a
/// pixel meet on the plane at `focus_distance` along the axis.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Lens {
    pub radius: f32,
    pub focus_distance: f32,
}

/// The sampler dimension of the lens sample: apart from the stream the integrators use, so a
/// pinhole render (which never reads it) keeps its dimension layout.
pub const LENS_DIM: u32 = 1 << 15;

impl Camera {
    /// A camera from a scene camera; the image's aspect ratio wins over the file's.
    pub fn new(cam: &scene::Camera, width: u32, height: u32) -> Self {
        let aspect = width as f32 / height.max(1) as f32;
        let kind = match cam.projection {
            Projection::Perspective { yfov, .. } => {
                Kind::Perspective { tan_half_y: super::math::tan(yfov.clamp(1e-4, 3.1) * 0.5), aspect }
            }
            Projection::Orthographic { xmag, ymag } => Kind::Orthographic { xmag: xmag.abs(), ymag: ymag.abs() },
        };
        Self::from_parts(cam.world_from_camera, kind, width, height)
    }

    /// The camera at shutter time `u` in [0, 1] between `open` and `close` (motion blur):
    /// position lerped, orientation slerped, field of view or extents lerped.
    pub fn interpolate(open: &scene::Camera, close: &scene::Camera, u: f32, width: u32, height: u32) -> Self {
        let (_, r0, t0) = open.world_from_camera.to_scale_rotation_translation();
        let (_, r1, t1) = close.world_from_camera.to_scale_rotation_translation();
        let r = pathfarm_common::scene::anim::slerp(&r0.to_array(), &r1.to_array(), u);
        let world_from_camera = Mat4::from_rotation_translation(glam::Quat::from_array(r), t0.lerp(t1, u));
        let lerp = |a: f32, b: f32| a + (b - a) * u;
        let projection = match (open.projection, close.projection) {
            (Projection::Perspective { yfov: a, aspect }, Projection::Perspective { yfov: b, .. }) => {
                Projection::Perspective { yfov: lerp(a, b), aspect }
            }
            (Projection::Orthographic { xmag: x0, ymag: y0 }, Projection::Orthographic { xmag: x1, ymag: y1 }) => {
                Projection::Orthographic { xmag: lerp(x0, x1), ymag: lerp(y0, y1) }
            }
            (p, _) => p,
        };
        Self::new(&scene::Camera { name: String::new(), world_from_camera, projection }, width, height)
    }

    fn from_parts(world_from_camera: Mat4, kind: Kind, width: u32, height: u32) -> Self {
        // Remove scale and shear: cameras are rigid.
        let (_, rot, trans) = world_from_camera.to_scale_rotation_translation();
        let world_from_camera = Affine3A::from_rotation_translation(rot.normalize(), trans);
        Self { camera_from_world: world_from_camera.inverse(), world_from_camera, kind, width, height, lens: None }
    }

    /// This camera with a thin lens; `None` unless it is a perspective camera and the lens is
    /// valid (radius > 0, focus distance > 0, both finite).
    pub fn with_lens(self, lens: Lens) -> Option<Self> {
        let ok = matches!(self.kind, Kind::Perspective { .. })
            && lens.radius.is_finite()
            && lens.radius > 0.0
            && lens.focus_distance.is_finite()
            && lens.focus_distance > 0.0;
        ok.then_some(Self { lens: Some(lens), ..self })
    }

    /// The camera ray of the current pixel sample: the film position from the sampler's next
    /// pair, the lens position (thin lens only) from [`LENS_DIM`].
    pub fn sample_ray(&self, pixel: UVec2, sampler: &mut impl Sampler) -> Ray {
        let u = sampler.get_pixel_2d();
        match self.lens {
            None => self.generate_ray(pixel, u),
            Some(lens) => self.generate_ray_lens(pixel, u, sampler.get_2d_at(LENS_DIM), lens),
        }
    }

    /// The thin-lens ray through `pixel` at offset `u`, from lens position `u_lens`.
    fn generate_ray_lens(&self, pixel: UVec2, u: Vec2, u_lens: Vec2, lens: Lens) -> Ray {
        let Kind::Perspective { tan_half_y, aspect } = self.kind else { return self.generate_ray(pixel, u) };
        let sx = 2.0 * (pixel.x as f32 + u.x) / self.width as f32 - 1.0;
        let sy = 1.0 - 2.0 * (pixel.y as f32 + u.y) / self.height as f32;
        // The pinhole ray's point on the plane of focus, reached from a point of the lens.
        let p_focus = Vec3A::new(sx * tan_half_y * aspect, sy * tan_half_y, -1.0) * lens.focus_distance;
        let disk = sample_uniform_disk_concentric(u_lens) * lens.radius;
        let p_lens = Vec3A::new(disk.x, disk.y, 0.0);
        let d = (p_focus - p_lens).normalize();
        Ray::new(
            self.world_from_camera.transform_point3a(p_lens),
            self.world_from_camera.transform_vector3a(d).normalize(),
        )
    }

    /// The thin lens, if any.
    pub fn lens(&self) -> Option<Lens> {
        self.lens
    }

    /// A perspective camera (40 degrees vertical) on the +Z side of `bounds`, looking down -Z,
    /// far enough that the bounding sphere fits.
    pub fn framing(bounds: Option<(Vec3, Vec3)>, width: u32, height: u32) -> Self {
        let aspect = width as f32 / height.max(1) as f32;
        Self::new(&scene::default_camera_for_bounds(bounds, aspect), width, height)
    }

    pub fn position(&self) -> Vec3A {
        self.world_from_camera.translation
    }

    /// The primary ray through `pixel` at offset `u` in [0, 1)^2 inside it (box filter).
    pub fn generate_ray(&self, pixel: UVec2, u: Vec2) -> Ray {
        match self.kind {
            Kind::Perspective { tan_half_y, aspect } => {
                let (x, y, z) =
                    self.perspective_direction(tan_half_y, aspect, pixel.x as f32, pixel.y as f32, u.x, u.y);
                Ray::new(self.world_from_camera.translation, Vec3A::new(x, y, z))
            }
            Kind::Orthographic { xmag, ymag } => {
                let sx = 2.0 * (pixel.x as f32 + u.x) / self.width as f32 - 1.0;
                let sy = 1.0 - 2.0 * (pixel.y as f32 + u.y) / self.height as f32;
                let o = self.world_from_camera.transform_point3a(Vec3A::new(sx * xmag, sy * ymag, 0.0));
                Ray::new(o, self.world_from_camera.transform_vector3a(-Vec3A::Z).normalize())
            }
        }
    }

    /// The world direction of the perspective camera ray through pixel (`px`, `py`) at offset
    /// (`ux`, `uy`), over lanes: glam's operations of the scalar ray spelled out (`normalize` is
    /// `v / sqrt((x x + y y) + z z)`, `transform_vector3a` is `(X x + Y y) + Z z`), so that
    /// [`Camera::pinhole_directions`] and [`Camera::generate_ray`] give the same bits.
    #[inline(always)]
    fn perspective_direction<R: Real>(&self, tan_half_y: f32, aspect: f32, px: R, py: R, ux: R, uy: R) -> (R, R, R) {
        let c = |v: f32| px.splat(v);
        let sx = c(2.0) * (px + ux) / c(self.width as f32) - c(1.0);
        let sy = c(1.0) - c(2.0) * (py + uy) / c(self.height as f32);
        let (dx, dy, dz) = normalize3(sx * c(tan_half_y) * c(aspect), sy * c(tan_half_y), c(-1.0));
        let m = &self.world_from_camera.matrix3;
        let (x, y, z) = (m.x_axis, m.y_axis, m.z_axis);
        normalize3(
            (c(x.x) * dx + c(y.x) * dy) + c(z.x) * dz,
            (c(x.y) * dx + c(y.y) * dy) + c(z.y) * dz,
            (c(x.z) * dx + c(y.z) * dy) + c(z.z) * dz,
        )
    }

    /// The directions of [`Camera::generate_ray`] for lanes of pixel coordinates (as f32) and
    /// offsets, where the camera is a pinhole ([`Camera::is_pinhole`]: every ray starts at
    /// [`Camera::position`]); `None` for other cameras.
    #[inline(always)]
    pub fn pinhole_directions<R: Real>(&self, px: R, py: R, ux: R, uy: R) -> Option<(R, R, R)> {
        match (self.kind, self.lens) {
            (Kind::Perspective { tan_half_y, aspect }, None) => {
                Some(self.perspective_direction(tan_half_y, aspect, px, py, ux, uy))
            }
            _ => None,
        }
    }

    /// Raster position of world point `p`, if it is in front of the camera and on the image.
    pub fn raster(&self, p: Vec3A) -> Option<Vec2> {
        let c = self.camera_from_world.transform_point3a(p);
        let (sx, sy) = match self.kind {
            Kind::Perspective { tan_half_y, aspect } => {
                if c.z >= 0.0 {
                    return None;
                }
                (c.x / -c.z / (tan_half_y * aspect), c.y / -c.z / tan_half_y)
            }
            Kind::Orthographic { xmag, ymag } => (c.x / xmag, c.y / ymag),
        };
        let x = (sx + 1.0) * 0.5 * self.width as f32;
        let y = (1.0 - sy) * 0.5 * self.height as f32;
        (x >= 0.0 && y >= 0.0 && x < self.width as f32 && y < self.height as f32).then_some(Vec2::new(x, y))
    }

    /// Pinhole importance for light tracing (pbrt-v4 `PerspectiveCamera::We` with a unit-area
    /// pixel normalization): returns (We, pdf_dir) for a world direction `w` leaving the camera,
    /// or `None` for an orthographic camera or a direction off the image. `We` is such that
    /// splatting `We * L * cos / pdf` onto raster pixels, divided by the pixel's sample count,
    /// estimates the pixel's mean radiance.
    pub fn importance(&self, w: Vec3A) -> Option<(f32, f32)> {
        let Kind::Perspective { tan_half_y, aspect } = self.kind else { return None };
        let d = self.camera_from_world.transform_vector3a(w);
        let cos = -d.z;
        if cos <= 0.0 {
            return None;
        }
        // Area of the image plane at distance 1, and of one pixel on it.
        let area = 4.0 * tan_half_y * tan_half_y * aspect;
        let cos2 = cos * cos;
        let pdf_dir = 1.0 / (area * cos2 * cos);
        let pixels = self.width as f32 * self.height as f32;
        Some((pixels / (area * cos2 * cos2), pdf_dir))
    }
}

/// An importance sample toward the camera from a reference point (pbrt's `CameraWiSample`).
#[derive(Clone, Copy, Debug)]
pub struct CameraWiSample {
    /// Importance `We` of the ray from the camera toward the point, normalized so that the sum
    /// of all splats divided by the samples per pixel estimates each pixel's mean radiance
    /// when every camera sample of every pixel traces one light path.
    pub we: f32,
    /// Unit direction from the reference point to the camera.
    pub wi: Vec3A,
    /// Density of the camera position per unit solid angle at the reference point.
    pub pdf: f32,
    /// The camera position and the raster position the point lands on.
    pub p_camera: Vec3A,
    pub raster: Vec2,
}

impl Camera {
    /// Whether light paths can be connected to the camera ([`Camera::sample_wi`] works): only
    /// the pinhole perspective camera (no thin lens).
    pub fn is_pinhole(&self) -> bool {
        matches!(self.kind, Kind::Perspective { .. }) && self.lens.is_none()
    }

    /// pbrt-v4 `PerspectiveCamera::We`: `1 / (A cos^4)` with `A` the whole image plane's area at
    /// distance 1 ([`Camera::importance`] without its per-pixel factor). With one light path per
    /// camera sample of every pixel, splats divided by the samples per pixel estimate each
    /// pixel's mean radiance. Zero off the image.
    pub fn we(&self, w: Vec3A) -> f32 {
        let c = self.position() + w;
        if self.raster(c).is_none() {
            return 0.0;
        }
        let pixels = self.width as f32 * self.height as f32;
        self.importance(w).map_or(0.0, |(we, _)| we / pixels)
    }

    /// Densities (position, direction) of a camera ray with direction `w` (pbrt's `PDF_We`):
    /// the pinhole's position is a delta (1); the direction is uniform on the image plane.
    pub fn pdf_we(&self, w: Vec3A) -> f32 {
        if self.raster(self.position() + w).is_none() {
            return 0.0;
        }
        self.importance(w).map_or(0.0, |(_, pdf)| pdf)
    }

    /// Samples the camera as seen from `p` (pbrt's `SampleWi` for a pinhole).
    pub fn sample_wi(&self, p: Vec3A) -> Option<CameraWiSample> {
        let p_camera = self.position();
        let d = p_camera - p;
        let dist2 = d.length_squared();
        if !(dist2 > 0.0) {
            return None;
        }
        let wi = d / dist2.sqrt();
        let raster = self.raster(p)?;
        let w_out = -wi;
        let we = self.we(w_out);
        if !(we > 0.0) {
            return None;
        }
        // Forward axis of the camera: the pinhole's "lens normal".
        let forward = self.world_from_camera.transform_vector3a(-Vec3A::Z).normalize();
        let cos = forward.dot(w_out);
        if !(cos > 0.0) {
            return None;
        }
        Some(CameraWiSample { we, wi, pdf: dist2 / cos, p_camera, raster })
    }
}

/// `v / |v|` as glam's `Vec3A::normalize` computes it: `v / sqrt((x x + y y) + z z)`.
#[inline(always)]
fn normalize3<R: Real>(x: R, y: R, z: R) -> (R, R, R) {
    let len = ((x * x + y * y) + z * z).sqrt();
    (x / len, y / len, z / len)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn center_ray_looks_down_minus_z_and_raster_inverts_generate_ray() {
        let cam = scene::Camera {
            name: "c".into(),
            world_from_camera: Mat4::from_translation(Vec3::new(0.0, 0.0, 3.9)),
            projection: Projection::Perspective { yfov: 0.686, aspect: None },
        };
        let c = Camera::new(&cam, 64, 32);
        let r = c.generate_ray(UVec2::new(32, 16), Vec2::ZERO);
        assert!((r.d - Vec3A::new(0.0, 0.0, -1.0)).length() < 1e-6);
        for (px, u) in [(UVec2::new(3, 5), Vec2::new(0.25, 0.75)), (UVec2::new(60, 30), Vec2::new(0.5, 0.5))] {
            let ray = c.generate_ray(px, u);
            let raster = c.raster(ray.at(2.0)).expect("on image");
            assert!((raster - (px.as_vec2() + u)).length() < 1e-3, "{raster}");
        }
    }

    #[test]
    fn we_is_normalized_and_sample_wi_finds_the_pixel() {
        use crate::render::chi2::TestRng;
        use crate::render::sampling::{sample_uniform_sphere, uniform_sphere_pdf};
        let cam = scene::Camera {
            name: "c".into(),
            world_from_camera: Mat4::from_translation(Vec3::new(0.2, 0.1, 3.9)),
            projection: Projection::Perspective { yfov: 0.7, aspect: None },
        };
        let c = Camera::new(&cam, 48, 32);
        // The integral of We cos over the sphere is 1 (Monte Carlo, 10^6 uniform directions:
        // the standard error is about 0.7%; bound 4%).
        let mut rng = TestRng::new(3);
        let n = 1_000_000;
        let forward = c.world_from_camera.transform_vector3a(-Vec3A::Z);
        let sum: f64 = (0..n)
            .map(|_| {
                let w = sample_uniform_sphere(rng.uniform_2d());
                f64::from(c.we(w) * forward.dot(w).max(0.0) / uniform_sphere_pdf())
            })
            .sum();
        let integral = sum / n as f64;
        assert!((integral - 1.0).abs() < 0.04, "integral of We cos = {integral}");
        // sample_wi from a point seen through a pixel lands on that pixel, with pdf_we consistent.
        let ray = c.generate_ray(UVec2::new(30, 7), Vec2::new(0.5, 0.5));
        let p = ray.at(3.0);
        let s = c.sample_wi(p).expect("visible");
        assert_eq!(s.raster.floor(), Vec2::new(30.0, 7.0));
        assert!((s.wi + ray.d).length() < 1e-4);
        assert!((s.pdf - 9.0 / forward.dot(ray.d)).abs() < 1e-3);
        assert!(c.pdf_we(ray.d) > 0.0 && c.pdf_we(-ray.d) == 0.0);
    }

    #[test]
    fn lens_positions_are_uniform_on_the_aperture_and_rays_meet_in_focus() {
        use crate::render::chi2::{Chi2Options, test_rect};
        let cam = scene::Camera {
            name: "c".into(),
            world_from_camera: Mat4::from_rotation_translation(
                glam::Quat::from_rotation_y(0.4),
                Vec3::new(1.0, 0.5, 2.0),
            ),
            projection: Projection::Perspective { yfov: 0.7, aspect: None },
        };
        let lens = Lens { radius: 0.3, focus_distance: 2.5 };
        let c = Camera::new(&cam, 32, 24).with_lens(lens).expect("perspective");
        let pixel = UVec2::new(5, 17);
        let u = Vec2::new(0.3, 0.6);
        let pinhole = c.generate_ray(pixel, u);
        let forward = c.world_from_camera.transform_vector3a(-Vec3A::Z);
        let focus = pinhole.at(lens.focus_distance / pinhole.d.dot(forward));
        // Chi-square (alpha 0.01, seed 5) of the ray origins in camera space against the uniform
        // density 1 / (pi r^2) on the disk; every ray passes through the pinhole ray's focus point.
        let r = lens.radius;
        let result = test_rect(
            "thin lens",
            |u_lens| {
                let ray = c.generate_ray_lens(pixel, u, u_lens, lens);
                let to_focus = (focus - ray.o).normalize();
                assert!((to_focus - ray.d).length() < 1e-4, "{to_focus} vs {}", ray.d);
                let o = c.camera_from_world.transform_point3a(ray.o);
                assert!(o.z.abs() < 1e-5);
                Some(Vec2::new(o.x, o.y))
            },
            |p| if p.length_squared() <= r * r { 1.0 / (std::f32::consts::PI * r * r) } else { 0.0 },
            (-r, r),
            (-r, r),
            &Chi2Options { samples: 400_000, res: (40, 40), seed: 5, ..Default::default() },
        );
        assert!(result.is_ok(), "{result:?}");
        // No lens on an orthographic camera, nor a zero or non-finite one.
        let ortho = scene::Camera { projection: Projection::Orthographic { xmag: 1.0, ymag: 1.0 }, ..cam.clone() };
        assert!(Camera::new(&ortho, 8, 8).with_lens(lens).is_none());
        assert!(Camera::new(&cam, 8, 8).with_lens(Lens { radius: 0.0, focus_distance: 1.0 }).is_none());
        assert!(Camera::new(&cam, 8, 8).with_lens(Lens { radius: 0.1, focus_distance: f32::NAN }).is_none());
    }

    /// A thin wall (1 x 4 x 4, thinnest along X) is framed face on from +X, a flat terrain
    /// from above, a cube from +Z; every corner of the bounds is on screen.
    #[test]
    fn framing_looks_along_the_thinnest_axis() {
        for (hi, view) in [
            (Vec3::new(0.5, 2.0, 2.0), Vec3A::NEG_X),
            (Vec3::new(2.0, 0.1, 2.0), Vec3A::NEG_Y),
            (Vec3::splat(2.0), Vec3A::NEG_Z),
        ] {
            let c = Camera::framing(Some((-hi, hi)), 64, 64);
            let forward = c.world_from_camera.transform_vector3a(Vec3A::NEG_Z);
            assert!((forward - view).length() < 1e-5, "bounds {hi}: looks along {forward}");
            for x in [-hi.x, hi.x] {
                for y in [-hi.y, hi.y] {
                    for z in [-hi.z, hi.z] {
                        assert!(c.raster(Vec3A::new(x, y, z)).is_some(), "bounds {hi}: corner off screen");
                    }
                }
            }
        }
    }

    #[test]
    fn framing_camera_sees_the_bounds() {
        let c = Camera::framing(Some((Vec3::splat(-2.0), Vec3::splat(2.0))), 100, 50);
        for corner in [Vec3A::splat(-2.0), Vec3A::splat(2.0), Vec3A::new(2.0, -2.0, 2.0)] {
            assert!(c.raster(corner).is_some(), "{corner} off screen");
        }
    }
}
