//! Cameras: pinhole perspective and orthographic, from the scene's glTF cameras, or a default
//! perspective camera framing the scene bounds.

use super::geometry::Ray;
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
}

impl Camera {
    /// A camera from a scene camera; the image's aspect ratio wins over the file's.
    pub fn new(cam: &scene::Camera, width: u32, height: u32) -> Self {
        let aspect = width as f32 / height.max(1) as f32;
        let kind = match cam.projection {
            Projection::Perspective { yfov, .. } => {
                Kind::Perspective { tan_half_y: (yfov.clamp(1e-4, 3.1) * 0.5).tan(), aspect }
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
        Self { camera_from_world: world_from_camera.inverse(), world_from_camera, kind, width, height }
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
        let sx = 2.0 * (pixel.x as f32 + u.x) / self.width as f32 - 1.0;
        let sy = 1.0 - 2.0 * (pixel.y as f32 + u.y) / self.height as f32;
        match self.kind {
            Kind::Perspective { tan_half_y, aspect } => {
                let d = Vec3A::new(sx * tan_half_y * aspect, sy * tan_half_y, -1.0).normalize();
                Ray::new(self.world_from_camera.translation, self.world_from_camera.transform_vector3a(d).normalize())
            }
            Kind::Orthographic { xmag, ymag } => {
                let o = self.world_from_camera.transform_point3a(Vec3A::new(sx * xmag, sy * ymag, 0.0));
                Ray::new(o, self.world_from_camera.transform_vector3a(-Vec3A::Z).normalize())
            }
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
    /// the pinhole perspective camera.
    pub fn is_pinhole(&self) -> bool {
        matches!(self.kind, Kind::Perspective { .. })
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
