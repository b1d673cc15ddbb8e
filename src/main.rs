//! `tcsense`: the command-line front end. Argument parsing, resolving arguments into the
//! crates' configs, printing — no physics here.

mod cmd;

use clap::{Parser, Subcommand};
use std::process::ExitCode;

/// Toolkit for ultrafast time-compressive CMOS image sensors (multitap charge modulators).
#[derive(Parser)]
#[command(name = "tcsense", version, about, long_about = None)]
struct Cli {
    /// Worker threads (default: all cores; 1 to 256).
    #[arg(long, global = true, value_parser = cmd::count_in(1, cmd::MAX_THREADS))]
    threads: Option<usize>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Exposure codes: generate, check, export to the sensor's code memory, import, show.
    #[command(subcommand)]
    Codes(cmd::codes::CodesCmd),
    /// Sensor model: the measurement matrix A.
    #[command(subcommand)]
    Sensor(cmd::sensor::SensorCmd),
    /// Simulate tap images y = A x (+ noise) from a transient cube.
    Simulate(cmd::sensor::SimulateArgs),
    /// Calibrate a real sensor from a laser-delay sweep: dark and gain maps per pixel and tap,
    /// the measured matrix A, and a report page; use it with --calibration DIR.
    Calibrate(cmd::calibrate::CalibrateArgs),
    /// Synthetic and imported transient datasets.
    #[command(subcommand)]
    Dataset(cmd::dataset::DatasetCmd),
    /// Decode tap images with any decoder by name: cubes, ranges or lifetimes.
    #[command(after_help = cmd::recon::decoder_listing())]
    Reconstruct(cmd::recon::ReconstructArgs),
    /// Train learned decoders.
    #[command(subcommand)]
    Train(cmd::train::TrainCmd),
    /// Depth (range) per return from a cube: peaks with parabolic sub-bin refinement.
    Depth(cmd::recon::DepthArgs),
    /// Lifetimes of a cube: a reconvolution fit of one or two exponentials (with the onset, the
    /// IRF and a background) to every pixel's decay, and the IRF-referenced phasor.
    Lifetime(cmd::recon::LifetimeArgs),
    /// Plots.
    #[command(subcommand)]
    Plot(cmd::recon::PlotCmd),
    /// Export trained decoders for deployment.
    #[command(subcommand)]
    Export(cmd::deploy::ExportCmd),
    /// Run an exported model (ONNX Runtime) on tap images: a frame, a stack or a directory,
    /// streamed, with products (cube, depth, peaks, point clouds, lifetimes).
    Infer(cmd::deploy::InferArgs),
    /// Compare decoders on a dataset split: MSE, PSNR, depth errors, lifetime error, time.
    #[command(after_help = cmd::recon::decoder_listing())]
    Eval(cmd::eval::EvalArgs),
    /// Design sweeps of the paper's Fig. 13 and Table 1 (TVAL3 MSE over a dataset).
    #[command(subcommand)]
    Sweep(cmd::sweep::SweepCmd),
    /// The main job end to end on built-in defaults: datasets, code design (selection and
    /// deep sensing), code-memory export, TVAL3, ADMM-Net and U-Net training, ONNX export,
    /// ONNX Runtime, and DIR/report.html with figures. Rerunning into DIR resumes.
    Demo(cmd::demo::DemoArgs),
    /// A sensor on the bench to decoders deployed for it: a delay sweep → calibration → the
    /// zoo's decoders fine-tuned to it within a budget → ONNX models that take its raw tap
    /// images → a check on held-back scenes and DIR/report.html. Rerunning into DIR resumes.
    Bringup(cmd::bringup::BringupArgs),
    /// Throughput benchmarks (prints figures).
    #[command(subcommand)]
    Bench(cmd::bench::BenchCmd),
    /// Trained decoders shipped with the toolkit: list them, show one's provenance; use them
    /// as `zoo:NAME` wherever a run is taken.
    #[command(subcommand)]
    Zoo(cmd::zoo::ZooCmd),
}

fn main() -> ExitCode {
    tcsense_kernels::quiet_broken_pipe();
    tcsense_kernels::keep_freed_memory();
    let cli = Cli::parse();
    if let Some(n) = cli.threads {
        if let Err(e) = rayon::ThreadPoolBuilder::new().num_threads(n).build_global() {
            eprintln!("error: cannot set up {n} threads: {e}");
            return ExitCode::from(2);
        }
    }
    let result = match cli.command {
        Command::Codes(c) => cmd::codes::run(c),
        Command::Sensor(c) => cmd::sensor::run(c),
        Command::Simulate(a) => cmd::sensor::simulate(a),
        Command::Calibrate(a) => cmd::calibrate::run(a),
        Command::Dataset(c) => cmd::dataset::run(c),
        Command::Reconstruct(c) => cmd::recon::reconstruct(c),
        Command::Train(c) => cmd::train::run(c),
        Command::Depth(a) => cmd::recon::depth(a),
        Command::Lifetime(a) => cmd::recon::lifetime(a),
        Command::Plot(c) => cmd::recon::plot(c),
        Command::Sweep(c) => cmd::sweep::sweep(c),
        Command::Eval(a) => cmd::eval::run(a),
        Command::Export(c) => cmd::deploy::export(c),
        Command::Infer(a) => cmd::deploy::infer(a, cli.threads),
        Command::Demo(a) => cmd::demo::run(a),
        Command::Bringup(a) => cmd::bringup::run(a),
        Command::Bench(c) => cmd::bench::run(c),
        Command::Zoo(c) => cmd::zoo::run(c),
    };
    match result {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::from(2)
        }
    }
}
