//! Camera images from ROS 2, checked before they become chunkrt frames: a `sensor_msgs/Image`
//! whose encoding, size or `step` lies, or that is larger than the configured camera, is refused
//! with a typed reason; a `sensor_msgs/CompressedImage` is decoded (JPEG, PNG) within the
//! configured size and a memory cap. The rows are packed (no padding) into the frame.

use chunkrt_ipc::{ENCODING_BGR8, ENCODING_MONO8, ENCODING_RGB8};

use crate::msg;

/// Why an image was refused.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ImageError {
    /// Not `rgb8`, `bgr8` or `mono8`.
    Encoding(String),
    /// Zero width or height.
    Empty,
    /// Larger than the configured camera.
    TooLarge {
        width: u32,
        height: u32,
        max_width: u32,
        max_height: u32,
    },
    /// `step` shorter than a row, or longer than twice a row and some alignment.
    Step { step: u32, row: u64 },
    /// `data` is not `step × height` bytes.
    Length { len: usize, expected: u64 },
    /// Compressed data larger than the cap.
    CompressedTooLarge { len: usize, max: usize },
    /// The compressed image does not decode (or is not JPEG / PNG).
    Decode(String),
}

impl std::fmt::Display for ImageError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ImageError::Encoding(e) => {
                let short: String = e.chars().take(32).collect();
                write!(f, "encoding {short:?}: rgb8, bgr8 or mono8 only")
            }
            ImageError::Empty => write!(f, "an empty image"),
            ImageError::TooLarge {
                width,
                height,
                max_width,
                max_height,
            } => write!(
                f,
                "{width}x{height}, larger than the configured {max_width}x{max_height}"
            ),
            ImageError::Step { step, row } => write!(f, "step {step} for rows of {row} bytes"),
            ImageError::Length { len, expected } => {
                write!(f, "{len} bytes of data where step x height is {expected}")
            }
            ImageError::CompressedTooLarge { len, max } => {
                write!(f, "{len} bytes compressed, more than {max}")
            }
            ImageError::Decode(e) => write!(f, "does not decode: {e}"),
        }
    }
}

/// A checked image: packed rows in `out[..width*height*bpp]`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Packed {
    pub width: u32,
    pub height: u32,
    pub encoding: u32,
    pub bpp: u32,
}

impl Packed {
    /// Bytes of the packed image.
    pub fn len(&self) -> usize {
        self.width as usize * self.height as usize * self.bpp as usize
    }

    /// Whether it has no pixels (never, once checked).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

fn encoding_code(e: &str) -> Option<(u32, u32)> {
    match e {
        "rgb8" => Some((ENCODING_RGB8, 3)),
        "bgr8" => Some((ENCODING_BGR8, 3)),
        "mono8" => Some((ENCODING_MONO8, 1)),
        _ => None,
    }
}

/// Checks `m` against the camera's largest size; returns its shape (the pixels stay in `m`).
pub fn check_image(m: &msg::Image, max_width: u32, max_height: u32) -> Result<Packed, ImageError> {
    let (encoding, bpp) =
        encoding_code(&m.encoding).ok_or_else(|| ImageError::Encoding(m.encoding.clone()))?;
    if m.width == 0 || m.height == 0 {
        return Err(ImageError::Empty);
    }
    if m.width > max_width || m.height > max_height {
        return Err(ImageError::TooLarge {
            width: m.width,
            height: m.height,
            max_width,
            max_height,
        });
    }
    let row = m.width as u64 * bpp as u64;
    if (m.step as u64) < row || m.step as u64 > 2 * row + 64 {
        return Err(ImageError::Step { step: m.step, row });
    }
    let expected = m.step as u64 * m.height as u64;
    if m.data.len() as u64 != expected {
        return Err(ImageError::Length {
            len: m.data.len(),
            expected,
        });
    }
    Ok(Packed {
        width: m.width,
        height: m.height,
        encoding,
        bpp,
    })
}

/// Copies `m`'s rows, without their padding, into `out` (at least `p.len()` bytes).
pub fn pack(m: &msg::Image, p: &Packed, out: &mut [u8]) {
    let row = p.width as usize * p.bpp as usize;
    let step = m.step as usize;
    for (r, dst) in out
        .chunks_exact_mut(row)
        .take(p.height as usize)
        .enumerate()
    {
        dst.copy_from_slice(&m.data[r * step..r * step + row]);
    }
}

/// Decodes a JPEG or PNG within the camera's largest size and `max_bytes` of compressed data;
/// returns rgb8 (colour) or mono8 (grey) pixels.
pub fn decode(
    m: &msg::CompressedImage,
    max_width: u32,
    max_height: u32,
    max_bytes: usize,
) -> Result<(Packed, Vec<u8>), ImageError> {
    if m.data.len() > max_bytes {
        return Err(ImageError::CompressedTooLarge {
            len: m.data.len(),
            max: max_bytes,
        });
    }
    let format = if m.format.contains("png") {
        image::ImageFormat::Png
    } else if m.format.contains("jpeg") || m.format.contains("jpg") {
        image::ImageFormat::Jpeg
    } else {
        let short: String = m.format.chars().take(32).collect();
        return Err(ImageError::Decode(format!(
            "format {short:?}: jpeg or png only"
        )));
    };
    let mut reader = image::io::Reader::with_format(std::io::Cursor::new(&m.data), format);
    let mut limits = image::io::Limits::default();
    limits.max_image_width = Some(max_width);
    limits.max_image_height = Some(max_height);
    limits.max_alloc = Some(max_width as u64 * max_height as u64 * 8 + (1 << 20));
    reader.limits(limits);
    let img = reader
        .decode()
        .map_err(|e| ImageError::Decode(e.to_string()))?;
    let (width, height) = (img.width(), img.height());
    if width == 0 || height == 0 {
        return Err(ImageError::Empty);
    }
    if width > max_width || height > max_height {
        return Err(ImageError::TooLarge {
            width,
            height,
            max_width,
            max_height,
        });
    }
    if img.color().channel_count() == 1 {
        let g = img.to_luma8();
        Ok((
            Packed {
                width,
                height,
                encoding: ENCODING_MONO8,
                bpp: 1,
            },
            g.into_raw(),
        ))
    } else {
        let c = img.to_rgb8();
        Ok((
            Packed {
                width,
                height,
                encoding: ENCODING_RGB8,
                bpp: 3,
            },
            c.into_raw(),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn img(w: u32, h: u32, enc: &str, step: u32, len: usize) -> msg::Image {
        msg::Image {
            width: w,
            height: h,
            encoding: enc.into(),
            step,
            data: vec![7; len],
            ..Default::default()
        }
    }

    #[test]
    fn images_that_lie_are_refused() {
        assert!(check_image(&img(4, 2, "rgb8", 12, 24), 640, 480).is_ok());
        // padded rows are fine, and packed away
        let m = img(4, 2, "rgb8", 16, 32);
        let p = check_image(&m, 640, 480).unwrap();
        let mut out = vec![0; p.len()];
        pack(&m, &p, &mut out);
        assert_eq!(out.len(), 24);
        assert!(matches!(
            check_image(&img(4, 2, "rgba8", 16, 32), 640, 480),
            Err(ImageError::Encoding(_))
        ));
        assert!(matches!(
            check_image(&img(4, 2, "rgb8", 11, 22), 640, 480),
            Err(ImageError::Step { .. })
        ));
        assert!(matches!(
            check_image(&img(4, 2, "rgb8", 12, 23), 640, 480),
            Err(ImageError::Length { .. })
        ));
        assert!(matches!(
            check_image(&img(641, 1, "mono8", 641, 641), 640, 480),
            Err(ImageError::TooLarge { .. })
        ));
        assert_eq!(
            check_image(&img(0, 2, "mono8", 0, 0), 640, 480),
            Err(ImageError::Empty)
        );
        // a width that claims 100 MB in a small message
        assert!(check_image(&img(100_000, 1_000, "rgb8", 300_000, 10), 1 << 20, 1 << 20).is_err());
    }

    #[test]
    fn compressed_images_decode_within_limits() {
        let mut png = Vec::new();
        let px = image::RgbImage::from_pixel(8, 4, image::Rgb([10, 20, 30]));
        image::DynamicImage::ImageRgb8(px)
            .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
            .unwrap();
        let m = msg::CompressedImage {
            format: "png".into(),
            data: png,
            ..Default::default()
        };
        let (p, data) = decode(&m, 640, 480, 1 << 20).unwrap();
        assert_eq!((p.width, p.height, p.encoding), (8, 4, ENCODING_RGB8));
        assert_eq!(&data[..3], &[10, 20, 30]);
        assert!(matches!(
            decode(&m, 4, 4, 1 << 20),
            Err(ImageError::Decode(_) | ImageError::TooLarge { .. })
        ));
        assert!(matches!(
            decode(&m, 640, 480, 10),
            Err(ImageError::CompressedTooLarge { .. })
        ));
        let bad = msg::CompressedImage {
            format: "jpeg".into(),
            data: vec![1, 2, 3],
            ..Default::default()
        };
        assert!(matches!(
            decode(&bad, 640, 480, 1 << 20),
            Err(ImageError::Decode(_))
        ));
    }
}
