//! Where a stream's frames come from: one `.npy` frame or stack read frame by frame from
//! disk, or a directory of `.npy` frames and tap-image PNGs.

use super::*;

/// Where frames come from.
pub enum FrameSource {
    /// A `.npy` file, read frame by frame.
    Npy { path: PathBuf, file: File, header: NpyHeader, frames: usize, frame: [usize; 3], single: bool },
    /// A directory of frame files.
    Dir { files: Vec<PathBuf> },
}

impl FrameSource {
    /// Open a `.npy` frame or stack, or a directory of `.npy`/`.png` frames.
    pub fn open(path: &Path) -> Result<Self> {
        if path.is_dir() {
            let mut files: Vec<PathBuf> = std::fs::read_dir(path)
                .map_err(|e| file_err(path, e))?
                .flatten()
                .map(|e| e.path())
                .filter(|p| p.is_file() && matches!(p.extension().and_then(|e| e.to_str()), Some("npy" | "png")))
                .collect();
            files.sort();
            if files.is_empty() {
                return Err(file_err(path, "no frames: expected .npy [M, H, W] or 16-bit PNG [H, M·W] files in this directory"));
            }
            return Ok(FrameSource::Dir { files });
        }
        let mut file = File::open(path).map_err(|e| file_err(path, e))?;
        let mut head = vec![0u8; 4096];
        let n = read_up_to(&mut file, &mut head).map_err(|e| file_err(path, e))?;
        let header = parse_header(&head[..n]).map_err(|e| file_err(path, e))?;
        let (frames, frame, single) = match header.shape.as_slice() {
            &[m, h, w] => (1, [m, h, w], true),
            &[f, m, h, w] => (f, [m, h, w], false),
            s => return Err(file_err(path, format!("measurements of shape {s:?}; expected [M, H, W] or [F, M, H, W]"))),
        };
        if frames == 0 || frame.contains(&0) {
            return Err(file_err(
                path,
                format!(
                    "measurements of shape {:?} hold no tap image; expected [M, H, W] or [F, M, H, W] with every size ≥ 1",
                    header.shape
                ),
            ));
        }
        if header.fortran && frames > 1 {
            return Err(file_err(path, "a Fortran-order stack cannot be streamed; save it in C order (numpy.ascontiguousarray)"));
        }
        let need = header
            .shape
            .iter()
            .try_fold(header.size as u64, |acc, &d| acc.checked_mul(d as u64))
            .and_then(|b| b.checked_add(header.data_offset as u64));
        let Some(need) = need else {
            return Err(file_err(path, format!("measurements of shape {:?}: more bytes than a file can hold", header.shape)));
        };
        let have = file.metadata().map_err(|e| file_err(path, e))?.len();
        if have < need {
            return Err(file_err(
                path,
                format!("npy data truncated: shape {:?} of {} needs {need} bytes, the file has {have}", header.shape, header.descr),
            ));
        }
        Ok(FrameSource::Npy { path: path.to_path_buf(), file, header, frames, frame, single })
    }

    /// Frames in the source.
    pub fn len(&self) -> usize {
        match self {
            FrameSource::Npy { frames, .. } => *frames,
            FrameSource::Dir { files } => files.len(),
        }
    }

    /// Whether it holds no frame.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// A single `[M, H, W]` frame (outputs drop the frame axis).
    pub fn single(&self) -> bool {
        matches!(self, FrameSource::Npy { single: true, .. })
    }

    /// Frame `i`, `[M, H, W]`, and the file it came from; `taps` is the model's `M` (to split
    /// PNG tap strips).
    pub fn read(&mut self, i: usize, taps: usize) -> Result<(Array3<f32>, PathBuf)> {
        match self {
            FrameSource::Npy { path, file, header, frame, .. } => {
                let per = frame.iter().product::<usize>();
                if header.fortran {
                    let a = read_npy(path)?;
                    let a = a.into_dimensionality::<ndarray::Ix3>().map_err(|e| file_err(path, e))?;
                    return Ok((a, path.clone()));
                }
                let mut bytes = vec![0u8; per * header.size];
                file.seek(SeekFrom::Start((header.data_offset + i * per * header.size) as u64)).map_err(|e| file_err(path, e))?;
                file.read_exact(&mut bytes).map_err(|e| file_err(path, format!("frame {i}: {e}")))?;
                let mut v = vec![0f32; per];
                header.decode_into(&bytes, &mut v);
                let a = Array3::from_shape_vec((frame[0], frame[1], frame[2]), v).map_err(|e| file_err(path, e))?;
                Ok((a, path.clone()))
            }
            FrameSource::Dir { files } => {
                let p = files[i].clone();
                let a = if p.extension().and_then(|e| e.to_str()) == Some("png") {
                    read_png_taps(&p, taps)?
                } else {
                    let a = read_npy(&p)?;
                    let shape = a.shape().to_vec();
                    a.into_dimensionality::<ndarray::Ix3>()
                        .map_err(|_| file_err(&p, format!("a frame of shape {shape:?}; expected [M, H, W]")))?
                };
                Ok((a, p))
            }
        }
    }
}

fn read_up_to(f: &mut File, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut n = 0;
    while n < buf.len() {
        match f.read(&mut buf[n..])? {
            0 => break,
            k => n += k,
        }
    }
    Ok(n)
}

/// A grayscale PNG of `taps` tap images side by side, `[H, M·W]` → `[M, H, W]`.
pub fn read_png_taps(path: &Path, taps: usize) -> Result<Array3<f32>> {
    let file = File::open(path).map_err(|e| file_err(path, e))?;
    let mut decoder = png::Decoder::new(std::io::BufReader::new(file));
    decoder.set_transformations(png::Transformations::IDENTITY);
    let mut reader = decoder.read_info().map_err(|e| file_err(path, format!("not a readable PNG: {e}")))?;
    let (w_all, h) = (reader.info().width as usize, reader.info().height as usize);
    let (color, depth) = (reader.info().color_type, reader.info().bit_depth);
    if color != png::ColorType::Grayscale || !matches!(depth, png::BitDepth::Sixteen | png::BitDepth::Eight) {
        return Err(file_err(path, format!("a {color:?} PNG of {depth:?} bits; expected 8- or 16-bit grayscale tap images")));
    }
    if taps == 0 || w_all % taps != 0 {
        return Err(file_err(path, format!("width {w_all} is not a multiple of the model's M = {taps} taps (tap images side by side)")));
    }
    let size = reader.output_buffer_size().ok_or_else(|| file_err(path, "PNG too large"))?;
    let mut buf = vec![0u8; size];
    let info = reader.next_frame(&mut buf).map_err(|e| file_err(path, format!("PNG data: {e}")))?;
    let w = w_all / taps;
    let line = info.line_size;
    let mut a = Array3::<f32>::zeros((taps, h, w));
    for r in 0..h {
        let row = &buf[r * line..(r + 1) * line];
        for col in 0..w_all {
            let v = match depth {
                png::BitDepth::Sixteen => u16::from_be_bytes([row[2 * col], row[2 * col + 1]]) as f32,
                _ => row[col] as f32,
            };
            a[(col / w, r, col % w)] = v;
        }
    }
    Ok(a)
}
