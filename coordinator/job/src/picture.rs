//! PNG drawings: material maps (one colour per material, with a legend) and observation
//! matrices (log-scale heat maps with a colour bar). Text is drawn with an 8×8 bitmap font.

use anyhow::{Context, Result};
use image::{Rgb, RgbImage};
use ndarray::Array2;
use scatterfarm_model::MaterialTable;
use std::path::Path;

const WHITE: Rgb<u8> = Rgb([255, 255, 255]);
const BLACK: Rgb<u8> = Rgb([0, 0, 0]);

/// The colour a material is drawn in: fixed for the built-in names, a palette for the rest.
pub fn material_colour(name: &str, index: usize) -> Rgb<u8> {
    match name {
        "transmissive" => Rgb([235, 235, 235]),
        "opaque" => Rgb([25, 25, 25]),
        "moderate" => Rgb([70, 130, 180]),
        "mild" => Rgb([120, 190, 100]),
        "uniform" => Rgb([240, 175, 50]),
        "back" => Rgb([205, 70, 70]),
        _ => {
            let c = colorous::TABLEAU10[(index + 4) % colorous::TABLEAU10.len()];
            Rgb([c.r, c.g, c.b])
        }
    }
}

/// Draws `text` at (x, y) with the 8×8 font scaled by `scale`.
pub fn draw_text(img: &mut RgbImage, x: u32, y: u32, text: &str, scale: u32, colour: Rgb<u8>) {
    use font8x8::UnicodeFonts;
    for (n, ch) in text.chars().enumerate() {
        let glyph = font8x8::BASIC_FONTS
            .get(ch)
            .or_else(|| font8x8::BASIC_FONTS.get('?'))
            .unwrap_or([0; 8]);
        for (gy, bits) in glyph.iter().enumerate() {
            for gx in 0..8u32 {
                if bits & (1 << gx) == 0 {
                    continue;
                }
                for sy in 0..scale {
                    for sx in 0..scale {
                        let px = x + (n as u32 * 8 + gx) * scale + sx;
                        let py = y + gy as u32 * scale + sy;
                        if px < img.width() && py < img.height() {
                            img.put_pixel(px, py, colour);
                        }
                    }
                }
            }
        }
    }
}

fn fill(img: &mut RgbImage, x: u32, y: u32, w: u32, h: u32, colour: Rgb<u8>) {
    for py in y..(y + h).min(img.height()) {
        for px in x..(x + w).min(img.width()) {
            img.put_pixel(px, py, colour);
        }
    }
}

/// The material map alone: `grid × grid` cells, each `cell` pixels wide.
pub fn material_map(assignment: &[u16], grid: usize, table: &MaterialTable, cell: u32) -> RgbImage {
    let side = grid as u32 * cell;
    let mut img = RgbImage::new(side, side);
    for (i, &m) in assignment.iter().enumerate() {
        let (r, c) = ((i / grid) as u32, (i % grid) as u32);
        let name = table
            .materials
            .get(m as usize)
            .map(|m| m.name.as_str())
            .unwrap_or("?");
        fill(
            &mut img,
            c * cell,
            r * cell,
            cell,
            cell,
            material_colour(name, m as usize),
        );
    }
    img
}

/// Pixels per cell so a `grid`-wide map is about 512 pixels wide.
pub fn cell_size(grid: usize) -> u32 {
    (512 / grid.max(1) as u32).max(1)
}

/// Panels side by side under their titles, with a legend of `table` on the right.
pub fn panels_with_legend(panels: &[(&str, RgbImage)], table: &MaterialTable) -> RgbImage {
    let margin = 16u32;
    let title_h = 28u32;
    let legend_w = 40
        + 16 * table
            .materials
            .iter()
            .map(|m| m.name.len() as u32)
            .max()
            .unwrap_or(4);
    let panel_h = panels.iter().map(|(_, p)| p.height()).max().unwrap_or(0);
    let width = margin + panels.iter().map(|(_, p)| p.width() + margin).sum::<u32>() + legend_w;
    let height = (title_h + panel_h + 2 * margin).max(margin * 2 + 24 * table.len() as u32);
    let mut img = RgbImage::from_pixel(width, height, WHITE);
    let mut x = margin;
    for (title, panel) in panels {
        draw_text(&mut img, x, margin / 2, title, 2, BLACK);
        image::imageops::replace(
            &mut img,
            panel,
            i64::from(x),
            i64::from(margin / 2 + title_h),
        );
        x += panel.width() + margin;
    }
    for (i, m) in table.materials.iter().enumerate() {
        let y = margin / 2 + title_h + 24 * i as u32;
        fill(&mut img, x, y, 16, 16, BLACK);
        fill(&mut img, x + 1, y + 1, 14, 14, material_colour(&m.name, i));
        draw_text(&mut img, x + 24, y, &m.name, 2, BLACK);
    }
    img
}

/// An observation matrix as a log10 heat map (inferno) with a colour bar; zeros are black.
pub fn observation_heat_map(obs: &Array2<f32>) -> RgbImage {
    let (rows, cols) = obs.dim();
    let max = obs.iter().cloned().fold(0.0f32, f32::max);
    let min_pos = obs
        .iter()
        .cloned()
        .filter(|&v| v > 0.0)
        .fold(f32::INFINITY, f32::min);
    let (lo, hi) = if max > 0.0 {
        (f64::from(min_pos).log10(), f64::from(max).log10())
    } else {
        (0.0, 1.0)
    };
    let span = (hi - lo).max(1e-9);
    let scale = (1024 / rows.max(cols).max(1) as u32).max(1);
    let margin = 16u32;
    let bar_w = 120u32;
    let (w, h) = (cols as u32 * scale, rows as u32 * scale);
    let mut img = RgbImage::from_pixel(w + bar_w + 2 * margin, h + 2 * margin, WHITE);
    for ((i, j), &v) in obs.indexed_iter() {
        let colour = if v > 0.0 {
            let c = colorous::INFERNO.eval_continuous((f64::from(v).log10() - lo) / span);
            Rgb([c.r, c.g, c.b])
        } else {
            BLACK
        };
        fill(
            &mut img,
            margin + j as u32 * scale,
            margin + i as u32 * scale,
            scale,
            scale,
            colour,
        );
    }
    // Colour bar: top is the largest value.
    let bx = margin + w + margin;
    for y in 0..h {
        let t = 1.0 - f64::from(y) / f64::from(h.max(1));
        let c = colorous::INFERNO.eval_continuous(t);
        fill(&mut img, bx, margin + y, 24, 1, Rgb([c.r, c.g, c.b]));
    }
    draw_text(&mut img, bx + 30, margin, &format!("1e{hi:.1}"), 1, BLACK);
    draw_text(
        &mut img,
        bx + 30,
        margin + h.saturating_sub(8),
        &format!("1e{lo:.1}"),
        1,
        BLACK,
    );
    draw_text(&mut img, bx + 30, margin + h / 2, "log10 O", 1, BLACK);
    img
}

/// Saves a PNG atomically.
pub fn save_png(img: &RgbImage, path: &Path) -> Result<()> {
    crate::observation::write_atomically(path, |w| {
        let mut buf = std::io::Cursor::new(Vec::new());
        img.write_to(&mut buf, image::ImageFormat::Png)
            .context("cannot encode PNG")?;
        w.write_all(buf.get_ref())?;
        Ok(())
    })
    .with_context(|| format!("cannot write {}", path.display()))
}
