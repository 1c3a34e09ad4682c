fn main() {
    chunkrt_tools::cli::main_of(
        "monitor",
        "Live rates, latencies and values of chunkrt services",
        chunkrt_tools::monitor::run,
    );
}
