fn main() {
    chunkrt_tools::cli::main_of(
        "fake-camera",
        "Publishes synthetic camera frames over iceoryx2",
        chunkrt_tools::fake_camera::run,
    );
}
