//! `velox view PATH`: watch a 4D result in a browser (`velox_tasks::view` says what PATH may
//! be and what the page shows). The command checks PATH and the port before anything is
//! served, then serves until Ctrl-C, or writes the one-file page with `--html`.

use std::io::Write;
use std::net::{IpAddr, Ipv4Addr, SocketAddr, TcpListener};
use std::path::PathBuf;

use velox_io::write_bytes;
use velox_tasks::view::{View, ViewOptions};

use crate::CliResult;

#[derive(clap::Args)]
pub struct ViewArgs {
    /// A folder of per-frame Gaussian PLYs (gaussians_fFF.ply) or surface points
    /// (points_fFF.ply), another tool's numbered PLY sequence (frame_0000.ply, ...), a dataset
    /// scene folder, or one Gaussian PLY.
    path: PathBuf,
    /// Port to serve on (default: a free one, printed).
    #[arg(long)]
    port: Option<u16>,
    /// Address to bind: 127.0.0.1 keeps the page on this machine; 0.0.0.0 shares it with the
    /// network.
    #[arg(long, default_value_t = IpAddr::V4(Ipv4Addr::LOCALHOST))]
    host: IpAddr,
    /// The scene whose cameras the page offers (default: the scene a decode output names in
    /// its decode.json, or PATH itself when it is a scene).
    #[arg(long)]
    scene: Option<PathBuf>,
    /// A second result to show beside PATH, in step with it (anything PATH may be; default: the
    /// ground truth's points of the scene a decode output names).
    #[arg(long)]
    compare: Option<PathBuf>,
    /// Show PATH alone, without the default comparison.
    #[arg(long, conflicts_with = "compare")]
    no_compare: bool,
    /// Write the viewer with every frame inside it to this HTML file (opens offline, from
    /// disk) instead of serving.
    #[arg(long)]
    html: Option<PathBuf>,
}

pub fn run(a: &ViewArgs) -> CliResult<()> {
    let options = ViewOptions {
        path: a.path.clone(),
        scene: a.scene.clone(),
        compare: a.compare.clone(),
        no_compare: a.no_compare,
    };
    let view = View::open(&options).map_err(|e| -> Box<dyn std::error::Error> { e })?;
    if let Some(html) = &a.html {
        let page = view.page().map_err(|e| -> Box<dyn std::error::Error> { e })?;
        write_bytes(html, page.as_bytes())?;
        println!(
            "wrote {} ({}, {:.1} MB): open it in a browser",
            html.display(),
            view.title(),
            page.len() as f64 / 1e6
        );
        return Ok(());
    }
    let address = SocketAddr::new(a.host, a.port.unwrap_or(0));
    let listener = TcpListener::bind(address).map_err(|e| match e.kind() {
        std::io::ErrorKind::AddrInUse => {
            format!(
                "port {} on {} is in use: choose another with --port (or leave it out for a free one)",
                address.port(),
                a.host
            )
        }
        _ => format!("cannot listen on {address}: {e}"),
    })?;
    let bound = listener.local_addr()?;
    let extra = view.extras();
    let extra = if extra.is_empty() { String::new() } else { format!(" ({extra})") };
    println!("velox view: {}{extra} at http://{bound}/ (Ctrl-C stops)", view.title());
    std::io::stdout().flush()?;
    view.serve(listener);
    Ok(())
}
