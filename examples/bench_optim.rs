//! Milliseconds per step of the optimisation building blocks, with mimalloc as the allocator.
//! `cargo run --release --example bench_optim` (and `bench_optim_sysalloc` for the system allocator).

#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

#[path = "common/bench_optim_body.rs"]
mod body;

fn main() -> anyhow::Result<()> {
    reconstruct::allocator::keep_freed_pages();
    body::run("mimalloc")
}
