fn main() {
    chunkrt_tools::cli::main_of(
        "fake-robot",
        "A simulated N-DoF arm over iceoryx2",
        chunkrt_tools::fake_robot::run,
    );
}
