//! `pathfarm-coordinator demo`: a coordinator and local workers on 127.0.0.1 render the bundled
//! Cornell box (written by our own code) and leave `demo.exr` and `demo.png`.

use crate::client::Client;
use crate::local::LocalWorkers;
use crate::server::{Server, ServerConfig};
use anyhow::Context;
use pathfarm_common::job::{IntegratorSettings, LightSampling, MisHeuristic, RenderSettings};
use pathfarm_common::protocol::JobRequest;
use pathfarm_common::scene::demo::cornell_demo_glb;
use std::path::PathBuf;

#[derive(clap::Args, Debug, Clone)]
pub struct DemoArgs {
    /// Output folder for demo.exr, demo.png and the coordinator's data.
    #[arg(long, default_value = "pathfarm-demo")]
    pub out: PathBuf,
    /// Address to serve on (port 0 = any free port).
    #[arg(long, default_value = "127.0.0.1:0")]
    pub listen: std::net::SocketAddr,
    /// Local workers (they share the cores).
    #[arg(long, default_value_t = 2)]
    pub local_workers: usize,
    #[arg(long, default_value_t = 256)]
    pub width: u32,
    #[arg(long, default_value_t = 256)]
    pub height: u32,
    #[arg(long, default_value_t = 128)]
    pub spp: u32,
    /// Keep serving (dashboard and API) after the job is done, until Ctrl-C.
    #[arg(long)]
    pub keep_serving: bool,
}

pub fn run(args: DemoArgs) -> anyhow::Result<()> {
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    let data_dir = args.out.join("data");
    std::fs::create_dir_all(&data_dir).with_context(|| format!("creating {}", data_dir.display()))?;
    let server = rt.block_on(Server::start(ServerConfig::new(args.listen, data_dir.clone())))?;
    let url = server.url();
    eprintln!("pathfarm demo: coordinator at {url}  (dashboard: {url}/)");
    let mut workers = LocalWorkers::start(&url, None, args.local_workers, &data_dir.join("worker-cache"))?;
    let client = Client::new(&url, None)?;
    let scene = client.upload_scene(cornell_demo_glb())?;
    let mut settings = RenderSettings::new(args.width, args.height, args.spp);
    settings.integrator = IntegratorSettings::Path {
        max_depth: 8,
        rr_depth: 3,
        mis: MisHeuristic::Power,
        light_sampling: LightSampling::SolidAngle,
    };
    settings.tile_size = 32;
    let job = JobRequest {
        frames: None,
        order: Default::default(),
        scene_id: scene.scene_id,
        name: Some("cornell demo".into()),
        priority: 0,
        requires: Vec::new(),
        notify: None,
        settings,
    };
    let id = client.submit(&job)?;
    let info = client.wait(id, true)?;
    let exr = args.out.join("demo.exr");
    let png = args.out.join("demo.png");
    pathfarm_common::film::write_atomic(&exr, &client.image_exr(id)?)?;
    pathfarm_common::film::write_atomic(&png, &client.preview_png(id)?)?;
    eprintln!(
        "pathfarm demo: {} x {} at {} spp in {:.1} s ({:.2} Msamples/s); wrote {} and {}",
        info.settings.width,
        info.settings.height,
        info.settings.spp,
        info.elapsed_secs,
        info.samples_per_sec / 1e6,
        exr.display(),
        png.display()
    );
    if args.keep_serving {
        eprintln!("pathfarm demo: serving {url}/ until Ctrl-C");
        rt.block_on(server.run_until_signal())?;
    }
    workers.stop();
    Ok(())
}
