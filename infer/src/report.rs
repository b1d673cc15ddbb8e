//! The HTML report: a document of sections holding paragraphs, figures (PNG files beside
//! it) and tables, written as one self-contained HTML file (styles inline, no scripts or
//! fonts fetched from anywhere).
//!
//! Every number of a table that comes from a results file carries its source — the file
//! (relative to the report) and a JSON pointer into it — as `data-src` and `data-ptr`
//! attributes, and is formatted from the value read there ([`Cell::from_json`]), so a
//! reader (or a test) can check each printed number against the run's results. On load,
//! the page counts its images that decoded and writes `data-images="ok/all"` on `<body>`
//! (what `scripts/report_screenshot.sh` checks in headless Chromium).
//!
//! ```
//! use tcsense_infer::report::{Block, Cell, Report, Section, Table};
//! let results = serde_json::json!({"rows": [{"mse": 1.25e-3}]});
//! let cell = Cell::from_json("results.json", &results, "/rows/0/mse", tcsense_infer::report::Format::Sci(3));
//! assert_eq!(cell.text, "1.250e-3");
//! let report = Report {
//!     title: "Demo".into(),
//!     subtitle: String::new(),
//!     sections: vec![Section { id: "metrics".into(), title: "Metrics".into(), blocks: vec![Block::Table(Table {
//!         caption: "MSE".into(), headers: vec!["decoder".into(), "MSE".into()], rows: vec![vec![Cell::text("TVAL3"), cell]],
//!     })] }],
//! };
//! let html = report.to_html();
//! assert!(html.contains(r#"data-ptr="/rows/0/mse">1.250e-3<"#));
//! ```

use serde_json::Value;
use std::fmt::Write as _;
use std::path::Path;
use tcsense_sensor::npy::write_bytes;

use crate::Result;

/// How a number is printed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Format {
    /// Scientific with this many decimals of the mantissa: `1.250e-3`.
    Sci(usize),
    /// Fixed with this many decimals: `31.42`.
    Fixed(usize),
}

impl Format {
    /// `v` printed; NaN, infinities and missing values as an en dash.
    pub fn show(self, v: Option<f64>) -> String {
        match v {
            Some(v) if v.is_finite() => match self {
                Format::Sci(d) => format!("{v:.d$e}"),
                Format::Fixed(d) => format!("{v:.d$}"),
            },
            _ => "–".to_string(),
        }
    }
}

/// A table cell: text, and where its number comes from.
#[derive(Debug, Clone, PartialEq)]
pub struct Cell {
    pub text: String,
    /// `(file relative to the report, JSON pointer)` of the value printed.
    pub source: Option<(String, String)>,
}

impl Cell {
    /// A cell of plain text.
    pub fn text(s: impl Into<String>) -> Self {
        Cell { text: s.into(), source: None }
    }

    /// The number at `pointer` of `json` (the parsed contents of `file`), printed in `format`
    /// (a dash where it is missing or not a finite number), with its source.
    pub fn from_json(file: &str, json: &Value, pointer: &str, format: Format) -> Self {
        Cell { text: format.show(json.pointer(pointer).and_then(Value::as_f64)), source: Some((file.to_string(), pointer.to_string())) }
    }
}

/// A table with a caption and one header row.
#[derive(Debug, Clone, PartialEq)]
pub struct Table {
    pub caption: String,
    pub headers: Vec<String>,
    pub rows: Vec<Vec<Cell>>,
}

/// What a section holds.
#[derive(Debug, Clone, PartialEq)]
pub enum Block {
    /// A paragraph of plain text.
    Text(String),
    /// A PNG beside the report (`src` relative to it) with a caption.
    Figure {
        src: String,
        caption: String,
    },
    Table(Table),
    /// Preformatted text (commands, file listings).
    Code(String),
}

/// One section, with an anchor id.
#[derive(Debug, Clone, PartialEq)]
pub struct Section {
    pub id: String,
    pub title: String,
    pub blocks: Vec<Block>,
}

/// A whole report.
#[derive(Debug, Clone, PartialEq)]
pub struct Report {
    pub title: String,
    pub subtitle: String,
    pub sections: Vec<Section>,
}

const STYLE: &str = "
body { font-family: 'DejaVu Sans', 'Helvetica Neue', Arial, sans-serif; max-width: 1280px; margin: 2em auto; padding: 0 1.5em; color: #1b1b1b; line-height: 1.45; }
h1 { margin-bottom: 0.2em; } .subtitle { color: #555; margin-top: 0; }
h2 { border-bottom: 2px solid #d0d7de; padding-bottom: 0.2em; margin-top: 2em; }
nav ol { columns: 2; }
figure { margin: 1.2em 0; } figure img { max-width: 100%; border: 1px solid #e1e4e8; }
figcaption { color: #444; font-size: 0.92em; margin-top: 0.3em; }
table { border-collapse: collapse; margin: 1em 0; font-size: 0.92em; }
caption { text-align: left; font-weight: bold; padding-bottom: 0.4em; }
th, td { border: 1px solid #d0d7de; padding: 0.3em 0.6em; } th { background: #f3f5f7; }
td[data-ptr] { text-align: right; font-variant-numeric: tabular-nums; }
pre { background: #f6f8fa; padding: 0.8em; overflow-x: auto; font-size: 0.88em; }
";

const IMAGE_CHECK: &str = "window.addEventListener('load', function () {
  var all = document.images.length, ok = 0;
  for (var i = 0; i < all; i++) { if (document.images[i].complete && document.images[i].naturalWidth > 0) ok++; }
  document.body.setAttribute('data-images', ok + '/' + all);
});";

/// `s` with `& < > "` escaped for HTML text and attributes.
pub fn escape(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for ch in s.chars() {
        match ch {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            c => out.push(c),
        }
    }
    out
}

impl Report {
    /// The report as one HTML document.
    pub fn to_html(&self) -> String {
        let mut h = String::new();
        let _ = write!(h, "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n<title>{}</title>\n<style>{STYLE}</style>\n<script>{IMAGE_CHECK}</script>\n</head>\n<body>\n", escape(&self.title));
        let _ = writeln!(h, "<h1>{}</h1>", escape(&self.title));
        if !self.subtitle.is_empty() {
            let _ = writeln!(h, "<p class=\"subtitle\">{}</p>", escape(&self.subtitle));
        }
        h.push_str("<nav><ol>\n");
        for s in &self.sections {
            let _ = writeln!(h, "<li><a href=\"#{}\">{}</a></li>", escape(&s.id), escape(&s.title));
        }
        h.push_str("</ol></nav>\n");
        for s in &self.sections {
            let _ = writeln!(h, "<section id=\"{}\">\n<h2>{}</h2>", escape(&s.id), escape(&s.title));
            for b in &s.blocks {
                match b {
                    Block::Text(t) => {
                        let _ = writeln!(h, "<p>{}</p>", escape(t));
                    }
                    Block::Code(t) => {
                        let _ = writeln!(h, "<pre>{}</pre>", escape(t));
                    }
                    Block::Figure { src, caption } => {
                        let _ = writeln!(
                            h,
                            "<figure><img src=\"{}\" alt=\"{}\"><figcaption>{}</figcaption></figure>",
                            escape(src),
                            escape(caption),
                            escape(caption)
                        );
                    }
                    Block::Table(t) => {
                        let _ = writeln!(h, "<table>\n<caption>{}</caption>", escape(&t.caption));
                        h.push_str("<tr>");
                        for c in &t.headers {
                            let _ = write!(h, "<th>{}</th>", escape(c));
                        }
                        h.push_str("</tr>\n");
                        for row in &t.rows {
                            h.push_str("<tr>");
                            for c in row {
                                match &c.source {
                                    Some((file, ptr)) => {
                                        let _ = write!(
                                            h,
                                            "<td data-src=\"{}\" data-ptr=\"{}\">{}</td>",
                                            escape(file),
                                            escape(ptr),
                                            escape(&c.text)
                                        );
                                    }
                                    None => {
                                        let _ = write!(h, "<td>{}</td>", escape(&c.text));
                                    }
                                }
                            }
                            h.push_str("</tr>\n");
                        }
                        h.push_str("</table>\n");
                    }
                }
            }
            h.push_str("</section>\n");
        }
        h.push_str("</body>\n</html>\n");
        h
    }

    /// Write the report to `path` (atomically).
    pub fn write(&self, path: &Path) -> Result<()> {
        write_bytes(path, self.to_html().as_bytes())?;
        Ok(())
    }

    /// Every figure's `src`, in order.
    pub fn figures(&self) -> Vec<&str> {
        self.sections
            .iter()
            .flat_map(|s| s.blocks.iter())
            .filter_map(|b| if let Block::Figure { src, .. } = b { Some(src.as_str()) } else { None })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numbers_and_text_are_escaped_and_sourced() {
        assert_eq!(Format::Sci(2).show(Some(0.000123456)), "1.23e-4");
        assert_eq!(Format::Fixed(1).show(Some(31.46)), "31.5");
        assert_eq!(Format::Fixed(1).show(Some(f64::NAN)), "–");
        assert_eq!(Format::Fixed(1).show(None), "–");
        let v = serde_json::json!({"a": [1.5, null]});
        assert_eq!(Cell::from_json("r.json", &v, "/a/0", Format::Fixed(2)).text, "1.50");
        assert_eq!(Cell::from_json("r.json", &v, "/a/1", Format::Fixed(2)).text, "–");
        assert_eq!(Cell::from_json("r.json", &v, "/b", Format::Fixed(2)).text, "–");
        let r = Report {
            title: "A <b> & \"c\"".into(),
            subtitle: "s".into(),
            sections: vec![Section {
                id: "x".into(),
                title: "X".into(),
                blocks: vec![Block::Figure { src: "f.png".into(), caption: "1 < 2".into() }, Block::Text("a&b".into())],
            }],
        };
        let h = r.to_html();
        assert!(h.contains("<h1>A &lt;b&gt; &amp; &quot;c&quot;</h1>"));
        assert!(h.contains("<img src=\"f.png\" alt=\"1 &lt; 2\">"));
        assert!(h.contains("<p>a&amp;b</p>"));
        assert_eq!(r.figures(), vec!["f.png"]);
    }
}
