//! `render_local` renders several units of a pass at once and folds them in order: its film is
//! the fold of one unit at a time, bit for bit, whatever the thread count, with adaptive
//! sampling (masks from earlier passes), bdpt's splats and igi's shared VPL sets.

mod common;

use common::*;
use pathfarm_common::adaptive::AdaptiveSettings;
use pathfarm_common::assembly::FilmAssembly;
use pathfarm_common::film::Film;
use pathfarm_common::job::{IntegratorSettings, LightSampling, MisHeuristic, PassSchedule, RenderSettings};
use pathfarm_worker::render::{Renderer, render_local};

/// The fold of one unit at a time in canonical order (what `render_local` did before it
/// rendered units at once), with the same assembly.
fn one_unit_at_a_time(renderer: &Renderer) -> Film {
    let settings = renderer.settings();
    let plan = settings.plan();
    let mut asm = FilmAssembly::new(&plan, settings.width, settings.height);
    let adaptive = settings.adaptive.as_ref().map(|a| (a, settings.spp));
    for key in plan.units() {
        if asm.next_pass(key.tile as usize) != key.pass {
            continue;
        }
        let (tile, pass) = (plan.tiles[key.tile as usize], plan.passes[key.pass as usize]);
        let r = renderer.render_unit_masked(tile, pass, asm.mask(key.tile as usize)).expect("unit");
        asm.offer(&plan, adaptive, key, r.accum, r.splats);
    }
    asm.into_film().expect("the film")
}

fn settings(integrator: IntegratorSettings, adaptive: bool) -> RenderSettings {
    // 5 x 4 tiles (the last column and row cut short), passes of 1, 2, 4 and 1 samples.
    let mut s = RenderSettings::new(72, 56, 8);
    s.tile_size = 16;
    s.seed = 5;
    s.passes = PassSchedule::Doubling { first: 1, max: 4 };
    s.integrator = integrator;
    if adaptive {
        // A loose threshold, so that blocks converge after the first passes.
        s.adaptive = Some(AdaptiveSettings { threshold: 0.5, min_spp: 2 });
    }
    s
}

#[test]
fn units_rendered_at_once_fold_to_the_one_at_a_time_film() {
    let scene = file_scene(&reference().join("cornell_mitsuba.glb"));
    let path = IntegratorSettings::Path {
        max_depth: 6,
        rr_depth: 3,
        mis: MisHeuristic::Power,
        light_sampling: LightSampling::SolidAngle,
    };
    let cases = [
        ("path", settings(path.clone(), false)),
        ("path, adaptive", settings(path.clone(), true)),
        // Two tiles: a pass is one chunk, and the next pass's chunk holds the same tiles (its
        // masks wait for the fold of the chunk before).
        ("path, adaptive, 2 tiles", {
            let mut s = settings(path, true);
            s.tile_size = 64;
            s
        }),
        (
            "bdpt",
            settings(
                IntegratorSettings::Bdpt { max_depth: 5, mis: MisHeuristic::Power, rr_depth: 3, strategy: None },
                false,
            ),
        ),
        (
            "igi, adaptive",
            settings(
                IntegratorSettings::Igi { vpls: 16, vpl_sets: 2, g_limit: 10.0, bias_compensation: true, max_depth: 5 },
                true,
            ),
        ),
    ];
    let mut skipped = 0;
    for (name, s) in cases {
        let want = one_unit_at_a_time(&Renderer::new(&scene, &s).expect("renderer"));
        for threads in [1, 3] {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().expect("pool");
            // A fresh renderer: igi's VPL cache starts empty, as a job's does.
            let renderer = Renderer::new(&scene, &s).expect("renderer");
            let got = pool.install(|| render_local(&renderer, |_, _| {}));
            assert_eq!((got.width, got.height), (want.width, want.height), "{name}, {threads} threads");
            assert!(got.sums == want.sums, "{name}, {threads} threads: the film differs from one unit at a time");
        }
        // Adaptive cases must have skipped something, or they test no mask.
        if s.adaptive.is_some() {
            let samples = |f: &Film| f.sums.iter().map(|p| u64::from(p.weight)).sum::<u64>();
            let full = u64::from(s.width * s.height * s.spp);
            assert!(samples(&want) < full, "{name}: adaptive sampling skipped nothing");
            skipped += 1;
        }
    }
    assert_eq!(skipped, 3);
}
