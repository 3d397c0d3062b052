mod cmd;

fn main() {
    // Die quietly on a closed pipe (`canopy inspect x | head`) as Unix tools do, instead of
    // Rust's default of ignoring SIGPIPE and panicking in println!.
    #[cfg(unix)]
    // SAFETY: restoring the default disposition of SIGPIPE before any thread starts.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
    if let Err(e) = cmd::run() {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
