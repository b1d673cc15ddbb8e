//! What the correlation passes share: the geometry of a pass cut into bands ([`Plane`]), where
//! its source planes are read from ([`Source`]), a kernel laid out for the three-shift GEMMs
//! ([`Kernel`]), each thread's scratch buffer, an output several tasks write at once
//! ([`SharedOut`]), and the time counter of the multiply-add loops. The im2col GEMMs of
//! [`crate::conv`] and the direct loops of [`crate::direct`] both build on it, so neither
//! depends on the other for these.
#![allow(unsafe_code)] // `SharedOut` is Send + Sync; see its SAFETY note

use std::cell::RefCell;

/// Target size of one band's shifted-copy buffer, in `f32` (1 MiB: half the L2 of one core here).
pub(crate) const BAND_ELEMS: usize = 1 << 18;
/// Tasks to split a pass into at least (so two or more cores share even a small batch).
const MIN_TASKS: usize = 4;
/// Padding of each shifted row, in elements, so that rows a power of two apart do not all map
/// to the same cache sets.
const PAD: usize = 16;

/// Where the source channels of one correlation item are read from. The im2col copies read
/// their planes through this, so a gathered input (the delay taps) is never materialised.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Source {
    /// Item `i` is the contiguous `[c_src, H, W]` block `i` of the input.
    Items,
    /// Item `i = b·T + t` stacks three groups of `group` channels of a `[B·T, group, H, W]`
    /// input: its channel `j·group + c` is channel `c` of frame `b·T + (t + off[j]) mod T`.
    Delay { bins: usize, group: usize, off: [isize; 3] },
}

impl Source {
    /// Offset in the input of the plane of source channel `ci` of `item` (`c_src` channels an item).
    #[inline]
    pub(crate) fn plane(self, item: usize, ci: usize, c_src: usize, hw: usize) -> usize {
        match self {
            Source::Items => (item * c_src + ci) * hw,
            Source::Delay { bins, group, off } => {
                let (b, t) = (item / bins, item % bins);
                let (j, c) = (ci / group, ci % group);
                let tt = (t as isize + off[j]).rem_euclid(bins as isize) as usize;
                ((b * bins + tt) * group + c) * hw
            }
        }
    }

    /// Elements of the input that `items` items of `c_src` channels read from.
    pub(crate) fn input_len(self, items: usize, c_src: usize, hw: usize) -> usize {
        match self {
            Source::Items => items * c_src * hw,
            Source::Delay { group, .. } => items * group * hw,
        }
    }
}

/// Nanoseconds spent inside the convolutions' multiply-add loops since the process started
/// (the GEMM calls of `crate::conv`, the direct loops of `crate::direct`), summed over threads.
pub(crate) static CONV_NANOS: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);

/// The geometry of one correlation pass: `c_src` channels in, `c_dst` out, bands of `rows` rows.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Plane {
    pub(crate) batch: usize,
    pub(crate) c_src: usize,
    pub(crate) c_dst: usize,
    pub(crate) h: usize,
    pub(crate) w: usize,
    pub(crate) rows: usize,
}

impl Plane {
    /// The same pass in equal bands of at most `max_rows` rows, and at least [`MIN_TASKS`] tasks
    /// when the frame allows bands of 8 rows.
    pub(crate) fn banded(self, max_rows: usize) -> Plane {
        let h = self.h.max(1);
        let min_bands = MIN_TASKS.div_ceil(self.batch.max(1));
        let bands = h.div_ceil(max_rows.clamp(1, h)).max(min_bands.min(h / 8).max(1));
        Plane { rows: h.div_ceil(bands), ..self }
    }
    /// Bands of one item.
    pub(crate) fn bands(&self) -> usize {
        self.h.div_ceil(self.rows)
    }
    /// Rows `y0..y1` of band `j`.
    pub(crate) fn band(&self, j: usize) -> (usize, usize) {
        (j * self.rows, ((j + 1) * self.rows).min(self.h))
    }
    /// Row stride of the shifted copies of band `y0..y1`: its rows plus one above and below.
    pub(crate) fn ld(&self, y0: usize, y1: usize) -> usize {
        (y1 - y0 + 2) * self.w + PAD
    }
}

/// A kernel rearranged for the three-shift GEMMs: `k[ky][c_dst][c_src·3 + kx]`, plus the bias
/// as one more column of the `ky = 0` block (row stride `3·c_src + 1` throughout).
pub(crate) struct Kernel {
    pub(crate) k: Vec<f32>,
    pub(crate) c_dst: usize,
    pub(crate) c_src: usize,
}

impl Kernel {
    /// `w(d, s, t)` is the weight from source channel `s` to destination `d` at tap `t = 3·ky + kx`.
    pub(crate) fn new(c_dst: usize, c_src: usize, w: impl Fn(usize, usize, usize) -> f32, bias: Option<&[f32]>) -> Self {
        let ks = 3 * c_src + 1;
        let mut k = vec![0.0f32; 3 * c_dst * ks];
        for ky in 0..3 {
            for d in 0..c_dst {
                let row = &mut k[(ky * c_dst + d) * ks..(ky * c_dst + d + 1) * ks];
                for s in 0..c_src {
                    for kx in 0..3 {
                        row[s * 3 + kx] = w(d, s, ky * 3 + kx);
                    }
                }
                if ky == 0 {
                    row[3 * c_src] = bias.map_or(0.0, |b| b[d]);
                }
            }
        }
        Kernel { k, c_dst, c_src }
    }
}

thread_local! {
    /// One shifted-copy buffer per thread, grown on demand and reused by every later task.
    static SCRATCH: RefCell<Vec<f32>> = const { RefCell::new(Vec::new()) };
}

/// Run `f` on this thread's scratch buffer of at least `len` elements. `f` must not call back
/// into rayon (it would be re-entered on this thread while the buffer is borrowed).
pub(crate) fn with_scratch<R>(len: usize, f: impl FnOnce(&mut [f32]) -> R) -> R {
    SCRATCH.with(|s| {
        let mut s = s.borrow_mut();
        if s.len() < len {
            s.resize(len, 0.0);
        }
        f(&mut s[..len])
    })
}

/// An output buffer written by several tasks at once, each through a disjoint view.
#[derive(Clone, Copy)]
pub(crate) struct SharedOut {
    pub(crate) ptr: *mut f32,
    pub(crate) len: usize,
}

impl SharedOut {
    /// The base pointer, read through the whole value (so closures capture `SharedOut`, which
    /// is `Sync`, and not the bare pointer field).
    pub(crate) fn base(self) -> *mut f32 {
        self.ptr
    }
}
// SAFETY: `SharedOut` is only used by `conv::correlate`, the direct loops and `pixel::par_bands`, whose tasks
// write disjoint views of a buffer that the caller borrows mutably for the whole parallel loop.
unsafe impl Send for SharedOut {}
unsafe impl Sync for SharedOut {}
