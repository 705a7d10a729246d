fn main() -> std::process::ExitCode {
    loadgen::cli::main_with_args(std::env::args_os())
}
