//! `mfc-deploy`: see `mfc_deploy::cli`.

fn main() -> std::process::ExitCode {
    mfc_deploy::cli::main()
}
