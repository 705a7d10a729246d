//! The browser console, as its browser test runs it in a process of its own.

fn main() -> std::process::ExitCode {
    mfc_console::cli::main_with_args(std::env::args_os())
}
