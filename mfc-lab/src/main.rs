//! `mfc-lab`: see `mfc_lab::cli`.

fn main() -> std::process::ExitCode {
    mfc_lab::cli::main()
}
