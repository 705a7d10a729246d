//! `plant-agent`: see `plant_agent::cli`.

fn main() -> std::process::ExitCode {
    plant_agent::cli::main()
}
