//! `controller-service`: serve the devices of a configuration file over Zenoh until SIGINT
//! or SIGTERM. The whole command line lives in [`controller_service::cli`].

fn main() -> std::process::ExitCode {
    controller_service::cli::main_with_args(std::env::args_os())
}
