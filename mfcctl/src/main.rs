//! `mfcctl`: the operator's command line (see the library's `cli` module).

fn main() -> std::process::ExitCode {
    mfcctl::cli::main_with_args(std::env::args_os())
}
