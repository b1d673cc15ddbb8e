use burn::backend::flex::{Flex, FlexDevice, FlexTensor};
use burn::backend::ops::{ConvOptions, FloatTensorOps, ModuleOps};
use burn::tensor::{Distribution, TensorData};
use std::time::Instant;

fn rnd(shape: [usize; 4], s: f64) -> FlexTensor {
    Flex::float_from_data(TensorData::random::<f32, _, _>(shape, Distribution::Normal(0.0, s), &mut rand::rng()), &FlexDevice)
}

fn time<F: FnMut()>(name: &str, mut f: F) {
    f();
    let n = 20;
    let t = Instant::now();
    for _ in 0..n { f(); }
    println!("{name:>12}: {:.2} ms", t.elapsed().as_secs_f64() * 1e3 / n as f64);
}

fn main() {
    let (b, c, h, w) = (2, 32, 64, 64);
    let x = rnd([b, c, h, w], 1.0);
    let wt = rnd([c, c, 3, 3], 0.1);
    let g = rnd([b, c, h, w], 1.0);
    let opts = ConvOptions::new([1, 1], [1, 1], [1, 1], 1);
    time("fwd", || { let _ = Flex::conv2d(x.clone(), wt.clone(), None, opts.clone()); });
    time("x_backward", || { let _ = Flex::conv2d_x_backward(x.clone(), wt.clone(), g.clone(), opts.clone()); });
    time("w_backward", || { let _ = Flex::conv2d_weight_backward(x.clone(), wt.clone(), g.clone(), opts.clone()); });
    ours();
}

#[allow(dead_code)]
fn ours() {
    use tcsense_models::conv::Conv3x3;
    let d = Conv3x3 { batch: 2, c_in: 32, c_out: 32, height: 64, width: 64 };
    let x = vec![0.5f32; d.x_len()];
    let w = vec![0.1f32; d.w_len()];
    let g = vec![0.3f32; d.y_len()];
    let mut y = vec![0.0; d.y_len()];
    let mut dx = vec![0.0; d.x_len()];
    let mut dw = vec![0.0; d.w_len()];
    time("ours fwd", || d.forward(&x, &w, None, &mut y));
    time("ours bx", || d.backward_x(&g, &w, &mut dx));
    time("ours bw", || d.backward_w(&x, &g, &mut dw));
}
