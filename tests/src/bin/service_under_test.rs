//! The controller service, as the crash tests run it in a process of their own.

fn main() -> std::process::ExitCode {
    controller_service::cli::main_with_args(std::env::args_os())
}
