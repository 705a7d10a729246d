/// The same allocator as the controller service's, so that the anchor beside it in a
/// benchmark differs from it only in what it does, and the generator leaves the service
/// as much of the machine as it can.
#[global_allocator]
static ALLOC: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> std::process::ExitCode {
    loadgen::cli::main_with_args(std::env::args_os())
}
