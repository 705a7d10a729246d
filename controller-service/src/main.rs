//! `controller-service`: serve the devices of a configuration file over Zenoh until SIGINT
//! or SIGTERM. The whole command line lives in [`controller_service::cli`].

/// mimalloc: zenoh's receive threads allocate what the worker frees (decoded samples,
/// thousands per gateway batch), which glibc's allocator serves slowly across threads.
#[global_allocator]
static ALLOC: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> std::process::ExitCode {
    controller_service::cli::main_with_args(std::env::args_os())
}
