//! `mfc-console`: the operator's live console, served to a browser (see the crate docs).

fn main() -> std::process::ExitCode {
    mfc_console::cli::main_with_args(std::env::args_os())
}
