//! One bounce of the path integrator at a plain Lambertian surface, written once over
//! [`Real`]: `f32` for the reference, 8 AVX2 lanes for the wavefront (8 paths at a time).
//!
//! "Plain" is what [`super::material::shade`] turns into a bare [`super::bsdf::Bxdf::Lambertian`]
//! with a frame around the shading normal ([`is_plain_lambert`], a hit without tangents): the
//! Cornell box's materials, and glTF's with metallic and specular factors 0. The bounce does, per
//! path, exactly the f32 operations of `shade`, `nee_with_light`, `NeeSample::contribution`,
//! `RenderScene::shadow_ray`, `sample_scatter_ahead`, the throughput checks, Russian roulette and
//! `offset_ray_origin` (glam's orders included: `(x + y) + z` dot products, its `max_element`),
//! so a lane gives the scalar integrator's bits (`tests/wavefront.rs` renders Lambertian scenes
//! both ways, with back faces, vertex colours, both heuristics and roulette, and compares bits).

use super::math::Real;
use super::vec3::{dot, is_zero, neg, select3};
use super::wide::Vec3Lanes;
use pathfarm_common::scene::{Material, MaterialModel};
use std::f32::consts::FRAC_1_PI;

/// Whether [`super::material::shade`] makes material `m` a bare Lambertian BSDF (no texture
/// read, no layer, no lobe choice), its reflectance the base colour times the hit's colour.
pub fn is_plain_lambert(m: &Material) -> bool {
    let plain = !m.unlit && m.base_color_texture.is_none() && m.normal_texture.is_none();
    let gltf_diffuse = m.transmission == 0.0
        && m.transmission_texture.is_none()
        && m.metallic_roughness_texture.is_none()
        && m.metallic.clamp(0.0, 1.0) == 0.0
        && m.specular_factor.clamp(0.0, 1.0) == 0.0
        && !(m.clearcoat > 0.0)
        && !(m.sheen_color.max_element() > 0.0);
    plain
        && match m.model {
            MaterialModel::Lambert => true,
            MaterialModel::Gltf => gltf_diffuse,
            _ => false,
        }
}

/// A path at a plain Lambertian hit, with its light sample and numbers (components per axis).
#[derive(Clone, Copy)]
pub struct LambertIn<R: Real> {
    /// The hit point, its geometric and shading normals (as the hit gives them).
    pub p: [R; 3],
    pub ng: [R; 3],
    pub ns: [R; 3],
    /// The direction of the ray that arrived.
    pub d: [R; 3],
    /// The reflectance.
    pub r: [R; 3],
    pub beta: [R; 3],
    pub eta_scale: R,
    /// Whether the path has a light sample (light index picked and the point valid), and it:
    /// radiance, direction, solid-angle pdf, selection pmf, point and normal on the light.
    pub light: R::Mask,
    pub ls_l: [R; 3],
    pub ls_wi: [R; 3],
    pub ls_pdf: R,
    pub pmf: R,
    pub p_light: [R; 3],
    pub n_light: [R; 3],
    /// The cosine-hemisphere direction of the bounce's direction numbers.
    pub cosine: [R; 3],
    /// Whether Russian roulette plays after this bounce, and its number.
    pub roulette: R::Mask,
    pub u_rr: R,
}

/// What the bounce leaves.
#[derive(Clone, Copy)]
pub struct LambertOut<R: Real> {
    /// The normals turned toward the viewer (the AOV's normal is `ns`).
    pub ng: [R; 3],
    pub ns: [R; 3],
    /// Where the light sample contributes if its shadow ray is unoccluded: the ray and the
    /// contribution (without the throughput the path had).
    pub shadow: R::Mask,
    pub shadow_o: [R; 3],
    pub shadow_d: [R; 3],
    pub shadow_t_max: R,
    pub contribution: [R; 3],
    /// Where the path goes on: its throughput, the BSDF sample's pdf and the next ray.
    pub alive: R::Mask,
    pub beta: [R; 3],
    pub pdf: R,
    pub ray_o: [R; 3],
    pub ray_d: [R; 3],
}

/// SSE's `maxps(a, b)`: `a > b ? a : b`.
#[inline(always)]
fn max_ps<R: Real>(a: R, b: R) -> R {
    R::select(b.lt(a), a, b)
}

/// glam's `Vec3A::max_element`: `max(max(x, z), max(y, z))` in `maxps` order.
#[inline(always)]
fn max_element<R: Real>(a: [R; 3]) -> R {
    max_ps(max_ps(a[0], a[2]), max_ps(a[1], a[2]))
}

/// `offset_ray_origin(p, ng, w)`: `ng` turned to `w`'s side, then each component offset.
#[inline(always)]
fn offset_origin<R: Real>(p: [R; 3], ng: [R; 3], w: [R; 3]) -> [R; 3] {
    let n = select3(dot(ng, w).lt(p[0].splat(0.0)), neg(ng), ng);
    [p[0].offset_along(n[0]), p[1].offset_along(n[1]), p[2].offset_along(n[2])]
}

/// `geometry::shadow_segment(p0, n0, p1, Some(n1))`: both ends offset, the direction and the
/// distance just short of the target.
#[inline(always)]
pub(super) fn shadow_segment<R: Real>(p0: [R; 3], n0: [R; 3], p1: [R; 3], n1: [R; 3]) -> ([R; 3], [R; 3], R) {
    let seg = [p1[0] - p0[0], p1[1] - p0[1], p1[2] - p0[2]];
    let o = offset_origin(p0, n0, seg);
    let target = offset_origin(p1, n1, neg(seg));
    let dir = [target[0] - o[0], target[1] - o[1], target[2] - o[2]];
    let len = dot(dir, dir).sqrt();
    (o, [dir[0] / len, dir[1] / len, dir[2] / len], len * len.splat(1.0 - 1e-4))
}

/// The bounce (see the module documentation). `power`: the power heuristic weighs the light
/// sample against BSDF sampling, else the balance heuristic.
#[inline(always)]
pub fn bounce<R: Real>(b: &LambertIn<R>, power: bool) -> LambertOut<R> {
    let x = b.p[0];
    let (zero, one) = (x.splat(0.0), x.splat(1.0));
    let inv_pi = x.splat(FRAC_1_PI);
    // `shade`: normals toward the viewer, the shading normal on the geometric side.
    let wo = neg(b.d);
    let flip = !dot(b.ng, wo).gt(zero);
    let ng = select3(flip, neg(b.ng), b.ng);
    let ns = select3(flip, neg(b.ns), b.ns);
    let ns = select3(dot(ns, ng).lt(zero), ng, ns);
    // `Frame::from_z(ns)`.
    let sign = one.xor_bits(ns[2].sign_bit());
    let a = x.splat(-1.0) / (sign + ns[2]);
    let c = ns[0] * ns[1] * a;
    let fx = [one + sign * ns[0] * ns[0] * a, sign * c, -sign * ns[0]];
    let fy = [c, sign + ns[1] * ns[1] * a, -ns[1]];
    let fz = ns;
    let f_r = [b.r[0] * inv_pi, b.r[1] * inv_pi, b.r[2] * inv_pi];
    let wo_ng = dot(wo, ng);
    let wo_z = dot(wo, fz);
    let wo_up = wo_z.lt(zero);
    let wo_zero = wo_z.eq(zero);

    // `nee_with_light`: the light on the viewer's side, `f |cos|` nonzero.
    let same_side = (dot(b.ls_wi, ng) * wo_ng).gt(zero);
    let wi_z = dot(b.ls_wi, fz);
    let hemisphere = !wo_zero & (wo_z * wi_z).gt(zero);
    let cos_light = wi_z.abs();
    let f = [
        R::select(hemisphere, f_r[0], zero) * cos_light,
        R::select(hemisphere, f_r[1], zero) * cos_light,
        R::select(hemisphere, f_r[2], zero) * cos_light,
    ];
    let shadow = b.light & !is_zero(b.ls_l) & same_side & !is_zero(f);
    // `NeeSample::contribution` with the BSDF's pdf (cosine, mirrored below the surface).
    let light_pdf = b.pmf * b.ls_pdf;
    let bsdf_pdf = R::select(hemisphere, R::select(wo_up, -wi_z, wi_z) * inv_pi, zero);
    let ratio = R::select(bsdf_pdf.gt(zero), bsdf_pdf / light_pdf, zero);
    let heuristic = if power { one / (one + ratio * ratio) } else { one / (one + ratio) };
    let infinite = light_pdf.abs().eq(x.splat(f32::INFINITY));
    let w = R::select(infinite, one, R::select(light_pdf.gt(zero), heuristic, zero));
    let scale = w / light_pdf;
    let contribution = [f[0] * b.ls_l[0] * scale, f[1] * b.ls_l[1] * scale, f[2] * b.ls_l[2] * scale];
    let (shadow_o, shadow_d, shadow_t_max) = shadow_segment(b.p, ng, b.p_light, b.n_light);

    // `sample_scatter_ahead`: the cosine direction, mirrored below the surface.
    let pdf = b.cosine[2] * inv_pi;
    let local = select3(wo_up, neg(b.cosine), b.cosine);
    let wi = [
        fx[0] * local[0] + fy[0] * local[1] + fz[0] * local[2],
        fx[1] * local[0] + fy[1] * local[1] + fz[1] * local[2],
        fx[2] * local[0] + fy[2] * local[1] + fz[2] * local[2],
    ];
    let sampled = !wo_zero & pdf.gt(zero) & !is_zero(f_r) & !local[2].eq(zero);
    let reflected = !(dot(wi, ng) * wo_ng).le(zero);
    let cos_wi = dot(wi, fz).abs() / pdf;
    let weight = [f_r[0] * cos_wi, f_r[1] * cos_wi, f_r[2] * cos_wi];
    let beta = [b.beta[0] * weight[0], b.beta[1] * weight[1], b.beta[2] * weight[2]];
    let inf = x.splat(f32::INFINITY);
    let finite = beta[0].abs().lt(inf) & beta[1].abs().lt(inf) & beta[2].abs().lt(inf);
    let max = max_element(beta);
    let mut alive = sampled & reflected & max.gt(zero) & finite;
    // Russian roulette: `min(max * eta_scale, RR_MAX_SURVIVAL)` (`f32::min`: the cap where NaN).
    let survival = x.splat(super::integrator::RR_MAX_SURVIVAL);
    let q = max * b.eta_scale;
    let q = R::select(q.lt(survival), q, survival);
    alive = alive & !(b.roulette & b.u_rr.ge(q));
    let beta = select3(b.roulette, [beta[0] / q, beta[1] / q, beta[2] / q], beta);
    let ray_o = offset_origin(b.p, ng, wi);
    LambertOut { ng, ns, shadow, shadow_o, shadow_d, shadow_t_max, contribution, alive, beta, pdf, ray_o, ray_d: wi }
}

/// 8 paths' [`LambertIn`] (lane `i` is path `i`), for [`super::wide::Avx2::lambert_bounces`];
/// truth values as 1.0 (true) or 0.0.
#[derive(Clone, Copy, Default)]
pub struct LambertLanes {
    pub p: Vec3Lanes,
    pub ng: Vec3Lanes,
    pub ns: Vec3Lanes,
    pub d: Vec3Lanes,
    pub r: Vec3Lanes,
    pub beta: Vec3Lanes,
    pub eta_scale: [f32; 8],
    pub light: [f32; 8],
    pub ls_l: Vec3Lanes,
    pub ls_wi: Vec3Lanes,
    pub ls_pdf: [f32; 8],
    pub pmf: [f32; 8],
    pub p_light: Vec3Lanes,
    pub n_light: Vec3Lanes,
    pub cosine: Vec3Lanes,
    pub roulette: [f32; 8],
    pub u_rr: [f32; 8],
}

/// 8 paths' [`LambertOut`]; truth values as bits (lane `i`: bit `i`).
#[derive(Clone, Copy)]
pub struct LambertLaneOut {
    pub ng: Vec3Lanes,
    pub ns: Vec3Lanes,
    pub shadow: u32,
    pub shadow_o: Vec3Lanes,
    pub shadow_d: Vec3Lanes,
    pub shadow_t_max: [f32; 8],
    pub contribution: Vec3Lanes,
    pub alive: u32,
    pub beta: Vec3Lanes,
    pub pdf: [f32; 8],
    pub ray_o: Vec3Lanes,
    pub ray_d: Vec3Lanes,
}

/// The 8 bounces of `l` in lanes (called from [`super::wide::Avx2::lambert_bounces`], compiled
/// for AVX2). No closures (see `accel::Sheared::new`).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
pub(super) fn lane_bounces(avx2: super::wide::Avx2, l: &LambertLanes, power: bool) -> LambertLaneOut {
    use super::wide::F32x8;
    #[inline(always)]
    fn v3(avx2: super::wide::Avx2, a: &Vec3Lanes) -> [F32x8; 3] {
        avx2.vec3_lanes(&a.0)
    }
    #[inline(always)]
    fn a3(avx2: super::wide::Avx2, v: [F32x8; 3]) -> Vec3Lanes {
        Vec3Lanes(avx2.lanes_vec3(v))
    }
    let zero = avx2.f32x8(&[0.0; 8]);
    let input = LambertIn {
        p: v3(avx2, &l.p),
        ng: v3(avx2, &l.ng),
        ns: v3(avx2, &l.ns),
        d: v3(avx2, &l.d),
        r: v3(avx2, &l.r),
        beta: v3(avx2, &l.beta),
        eta_scale: avx2.f32x8(&l.eta_scale),
        light: avx2.f32x8(&l.light).gt(zero),
        ls_l: v3(avx2, &l.ls_l),
        ls_wi: v3(avx2, &l.ls_wi),
        ls_pdf: avx2.f32x8(&l.ls_pdf),
        pmf: avx2.f32x8(&l.pmf),
        p_light: v3(avx2, &l.p_light),
        n_light: v3(avx2, &l.n_light),
        cosine: v3(avx2, &l.cosine),
        roulette: avx2.f32x8(&l.roulette).gt(zero),
        u_rr: avx2.f32x8(&l.u_rr),
    };
    let o = bounce(&input, power);
    LambertLaneOut {
        ng: a3(avx2, o.ng),
        ns: a3(avx2, o.ns),
        shadow: o.shadow.bits(),
        shadow_o: a3(avx2, o.shadow_o),
        shadow_d: a3(avx2, o.shadow_d),
        shadow_t_max: o.shadow_t_max.to_array(),
        contribution: a3(avx2, o.contribution),
        alive: o.alive.bits(),
        beta: a3(avx2, o.beta),
        pdf: o.pdf.to_array(),
        ray_o: a3(avx2, o.ray_o),
        ray_d: a3(avx2, o.ray_d),
    }
}

#[cfg(all(test, target_arch = "x86_64"))]
mod tests {
    use super::*;
    use crate::render::wide::{Avx2, unit};

    /// A value for input `k` of case `i`: mostly random in [-1, 1], sometimes one of the values
    /// that take the kernel's other branches (zeros of both signs, NaN, infinities, tiny and
    /// huge numbers).
    fn value(i: u64, k: u64) -> f32 {
        let special = [0.0, -0.0, f32::NAN, f32::INFINITY, -f32::INFINITY, 1e-30, 1e30, 1.0, -1.0, 0.95];
        let u = unit(i * 97 + k);
        if u < 0.04 {
            special[(unit(i * 97 + k + 50) * special.len() as f32) as usize % special.len()]
        } else {
            u * 2.0 - 1.0
        }
    }

    /// The 8-lane bounce (AVX2) is the `f32` bounce in every lane, bit for bit, on random and
    /// degenerate inputs: back faces, grazing and zero directions, NaN and infinite values,
    /// both heuristics, with and without roulette. (The `f32` bounce is the scalar integrator's:
    /// `tests/wavefront.rs` compares whole renders.)
    #[test]
    fn lanes_are_the_scalar_bounce() {
        let Some(avx2) = Avx2::new() else { return };
        let mut compared = 0;
        for case in 0..4000u64 {
            let mut lanes = LambertLanes::default();
            let mut inputs = Vec::new();
            for j in 0..8 {
                let i = case * 8 + j as u64;
                let v = |k: u64| value(i, k);
                let v3 = |k: u64| glam::Vec3A::new(v(k), v(k + 1), v(k + 2));
                let unit3 = |k: u64| v3(k).normalize_or(glam::Vec3A::Z);
                let input = LambertIn::<f32> {
                    p: v3(0).to_array(),
                    ng: unit3(3).to_array(),
                    ns: unit3(6).to_array(),
                    d: unit3(9).to_array(),
                    r: v3(12).abs().to_array(),
                    beta: v3(15).abs().to_array(),
                    eta_scale: v(18).abs() + 0.5,
                    light: v(19) > -0.8,
                    ls_l: v3(20).abs().to_array(),
                    ls_wi: unit3(23).to_array(),
                    ls_pdf: v(26).abs() * 4.0,
                    pmf: v(27).abs(),
                    p_light: v3(28).to_array(),
                    n_light: unit3(31).to_array(),
                    cosine: unit3(34).to_array(),
                    roulette: v(37) > 0.0,
                    u_rr: v(38).abs(),
                };
                let f = |a: [f32; 3]| glam::Vec3A::from_array(a);
                lanes.p.set(j, f(input.p));
                lanes.ng.set(j, f(input.ng));
                lanes.ns.set(j, f(input.ns));
                lanes.d.set(j, f(input.d));
                lanes.r.set(j, f(input.r));
                lanes.beta.set(j, f(input.beta));
                lanes.eta_scale[j] = input.eta_scale;
                lanes.light[j] = if input.light { 1.0 } else { 0.0 };
                lanes.ls_l.set(j, f(input.ls_l));
                lanes.ls_wi.set(j, f(input.ls_wi));
                lanes.ls_pdf[j] = input.ls_pdf;
                lanes.pmf[j] = input.pmf;
                lanes.p_light.set(j, f(input.p_light));
                lanes.n_light.set(j, f(input.n_light));
                lanes.cosine.set(j, f(input.cosine));
                lanes.roulette[j] = if input.roulette { 1.0 } else { 0.0 };
                lanes.u_rr[j] = input.u_rr;
                inputs.push(input);
            }
            let power = case % 2 == 0;
            let got = avx2.lambert_bounces(&lanes, power);
            for (j, input) in inputs.iter().enumerate() {
                let want = bounce(input, power);
                // NaNs compare as one value: their payloads follow operand orders the compiler
                // picks, and nothing downstream reads them (comparisons with NaN are false).
                let bits = |x: f32| if x.is_nan() { f32::NAN.to_bits() } else { x.to_bits() };
                let bits3 = |a: [f32; 3]| a.map(bits);
                let lane3 = |a: &Vec3Lanes| bits3(a.get(j).to_array());
                let at = format!("case {case} lane {j}");
                assert_eq!(got.shadow & (1 << j) != 0, want.shadow, "{at}: shadow");
                assert_eq!(got.alive & (1 << j) != 0, want.alive, "{at}: alive");
                assert_eq!(lane3(&got.ng), bits3(want.ng), "{at}: ng");
                assert_eq!(lane3(&got.ns), bits3(want.ns), "{at}: ns");
                if want.shadow {
                    assert_eq!(lane3(&got.shadow_o), bits3(want.shadow_o), "{at}: shadow origin");
                    assert_eq!(lane3(&got.shadow_d), bits3(want.shadow_d), "{at}: shadow direction");
                    assert_eq!(bits(got.shadow_t_max[j]), bits(want.shadow_t_max), "{at}: t_max");
                    assert_eq!(lane3(&got.contribution), bits3(want.contribution), "{at}: contribution");
                }
                if want.alive {
                    assert_eq!(lane3(&got.beta), bits3(want.beta), "{at}: beta");
                    assert_eq!(bits(got.pdf[j]), bits(want.pdf), "{at}: pdf");
                    assert_eq!(lane3(&got.ray_o), bits3(want.ray_o), "{at}: ray origin");
                    assert_eq!(lane3(&got.ray_d), bits3(want.ray_d), "{at}: ray direction");
                }
                compared += 1;
            }
        }
        assert_eq!(compared, 32_000);
    }
}
