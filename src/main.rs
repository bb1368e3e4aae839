fn main() {
    println!("reconstruct: under construction");
}
