//! `bench_optim` with the system allocator, to compare against mimalloc.

#[path = "common/bench_optim_body.rs"]
mod body;

fn main() -> anyhow::Result<()> {
    body::run("system")
}
