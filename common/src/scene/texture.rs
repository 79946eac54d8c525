//! Textures: decoded to linear float RGBA, sampled bilinearly with glTF wrap modes and
//! KHR_texture_transform.

use glam::{Vec2, Vec4};

/// glTF sampler wrap modes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Default)]
pub enum WrapMode {
    #[default]
    Repeat,
    MirroredRepeat,
    ClampToEdge,
}

/// KHR_texture_transform: `uv' = T(offset) R(rotation) S(scale) uv`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TextureTransform {
    pub offset: Vec2,
    pub rotation: f32,
    pub scale: Vec2,
}

impl Default for TextureTransform {
    fn default() -> Self {
        Self { offset: Vec2::ZERO, rotation: 0.0, scale: Vec2::ONE }
    }
}

impl TextureTransform {
    /// Applies the transform (the extension's matrix, rotation counter-clockwise in UV space).
    pub fn apply(&self, uv: Vec2) -> Vec2 {
        let s = uv * self.scale;
        let (sin, cos) = self.rotation.sin_cos();
        Vec2::new(cos * s.x + sin * s.y, -sin * s.x + cos * s.y) + self.offset
    }
}

/// A decoded texture in linear RGBA.
#[derive(Clone, Debug)]
pub struct Texture {
    pub name: String,
    pub width: u32,
    pub height: u32,
    /// Row-major, top row first (glTF UV (0, 0) is the image's top-left corner). Shared by the
    /// textures of one image in one colour space (they differ only in wrap modes).
    pub texels: std::sync::Arc<Vec<Vec4>>,
    pub wrap_s: WrapMode,
    pub wrap_t: WrapMode,
}

fn wrap(i: i64, n: u32, mode: WrapMode) -> u32 {
    let n = i64::from(n.max(1));
    let r = match mode {
        WrapMode::Repeat => i.rem_euclid(n),
        WrapMode::ClampToEdge => i.clamp(0, n - 1),
        WrapMode::MirroredRepeat => {
            let p = i.rem_euclid(2 * n);
            if p < n { p } else { 2 * n - 1 - p }
        }
    };
    r as u32
}

impl Texture {
    fn texel(&self, x: i64, y: i64) -> Vec4 {
        let x = wrap(x, self.width, self.wrap_s);
        let y = wrap(y, self.height, self.wrap_t);
        self.texels.get((y * self.width + x) as usize).copied().unwrap_or(Vec4::ONE)
    }

    /// Bilinear lookup at `uv` (texel centres at half-integers).
    pub fn sample(&self, uv: Vec2) -> Vec4 {
        if self.width == 0 || self.height == 0 || !uv.is_finite() {
            return Vec4::ONE;
        }
        let x = uv.x * self.width as f32 - 0.5;
        let y = uv.y * self.height as f32 - 0.5;
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        let (x0, y0) = (x0 as i64, y0 as i64);
        let a = self.texel(x0, y0).lerp(self.texel(x0 + 1, y0), fx);
        let b = self.texel(x0, y0 + 1).lerp(self.texel(x0 + 1, y0 + 1), fx);
        a.lerp(b, fy)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wrap_modes() {
        assert_eq!(wrap(-1, 4, WrapMode::Repeat), 3);
        assert_eq!(wrap(5, 4, WrapMode::ClampToEdge), 3);
        assert_eq!(wrap(4, 4, WrapMode::MirroredRepeat), 3);
        assert_eq!(wrap(-1, 4, WrapMode::MirroredRepeat), 0);
    }

    #[test]
    fn bilinear_midpoint() {
        let t = Texture {
            name: "t".into(),
            width: 2,
            height: 1,
            texels: std::sync::Arc::new(vec![Vec4::ZERO, Vec4::ONE]),
            wrap_s: WrapMode::ClampToEdge,
            wrap_t: WrapMode::ClampToEdge,
        };
        assert!((t.sample(Vec2::new(0.5, 0.5)).x - 0.5).abs() < 1e-6);
        assert_eq!(t.sample(Vec2::new(0.0, 0.5)).x, 0.0);
    }
}
