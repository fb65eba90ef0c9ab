//! Reading a table of text: a header row of column names, then rows of cells; `#` comment
//! lines and blank lines anywhere; cells separated by commas, semicolons, tabs or runs of
//! whitespace (detected from the header unless given). In the delimited forms a cell may be
//! quoted (`"a, b"`, `""` for a quote inside), and an empty cell is a cell: it says "no value
//! here". A UTF-8 byte-order mark and CR line ends are accepted; bytes that are not UTF-8
//! become U+FFFD (and then fail as numbers, with their line and column).
use std::io::BufRead;

/// How the cells of a row are separated.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Delimiter {
    /// `,`.
    Comma,
    /// `;` (spreadsheets of locales with a decimal comma; the numbers still need a point).
    Semicolon,
    /// A tab.
    Tab,
    /// Runs of spaces and tabs (no empty cells, no quoting).
    Whitespace,
}

impl Delimiter {
    /// Its name: `comma`, `semicolon`, `tab`, `whitespace`.
    pub fn name(self) -> &'static str {
        match self {
            Delimiter::Comma => "comma",
            Delimiter::Semicolon => "semicolon",
            Delimiter::Tab => "tab",
            Delimiter::Whitespace => "whitespace",
        }
    }

    fn char(self) -> Option<char> {
        match self {
            Delimiter::Comma => Some(','),
            Delimiter::Semicolon => Some(';'),
            Delimiter::Tab => Some('\t'),
            Delimiter::Whitespace => None,
        }
    }

    /// The delimiter a header line uses: a tab, else a semicolon, else a comma, else
    /// whitespace.
    pub fn detect(header: &str) -> Delimiter {
        if header.contains('\t') {
            Delimiter::Tab
        } else if header.contains(';') {
            Delimiter::Semicolon
        } else if header.contains(',') {
            Delimiter::Comma
        } else {
            Delimiter::Whitespace
        }
    }
}

impl std::str::FromStr for Delimiter {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "comma" | "," => Ok(Delimiter::Comma),
            "semicolon" | ";" => Ok(Delimiter::Semicolon),
            "tab" | "\t" | "\\t" => Ok(Delimiter::Tab),
            "whitespace" | "space" | " " => Ok(Delimiter::Whitespace),
            _ => Err(format!(
                "delimiter `{s}`: comma, semicolon, tab or whitespace"
            )),
        }
    }
}

/// A table being read row by row; the cells of the current row are borrowed from it.
pub(crate) struct Table<R> {
    input: R,
    raw: Vec<u8>,
    line: String,
    /// Line number of the current line, 1-based.
    pub line_no: usize,
    pub delimiter: Delimiter,
    pub header: Vec<String>,
    pub header_line: usize,
    /// The current row's cells, unquoted and trimmed, as ranges of `cells_text`.
    cells_text: String,
    cells: Vec<(usize, usize)>,
}

/// What went wrong reading the table before its rows.
#[derive(Debug)]
pub(crate) enum OpenError {
    Io(std::io::Error),
    /// No header row (the file is empty or holds only comments).
    NoHeader,
    /// The header row does not split (an unclosed quote).
    BadHeader {
        line: usize,
        reason: String,
    },
}

/// The next row: its line number, or a row that does not split (its line and why).
pub(crate) enum Next {
    Row(usize),
    Bad(usize, String),
    End,
}

impl<R: BufRead> Table<R> {
    /// Reads up to the header row (the first line that is neither blank nor a comment).
    pub fn open(input: R, delimiter: Option<Delimiter>) -> Result<Table<R>, OpenError> {
        let mut t = Table {
            input,
            raw: Vec::new(),
            line: String::new(),
            line_no: 0,
            delimiter: Delimiter::Comma,
            header: Vec::new(),
            header_line: 0,
            cells_text: String::new(),
            cells: Vec::new(),
        };
        loop {
            if !t.next_line().map_err(OpenError::Io)? {
                return Err(OpenError::NoHeader);
            }
            if !is_skipped(&t.line) {
                break;
            }
        }
        t.delimiter = delimiter.unwrap_or_else(|| Delimiter::detect(&t.line));
        t.header_line = t.line_no;
        let line = std::mem::take(&mut t.line);
        t.split(&line).map_err(|reason| OpenError::BadHeader {
            line: t.header_line,
            reason,
        })?;
        t.header = (0..t.cells.len()).map(|i| t.cell(i).to_string()).collect();
        Ok(t)
    }

    /// Reads the next line into `self.line`; false at the end.
    fn next_line(&mut self) -> std::io::Result<bool> {
        self.raw.clear();
        if self.input.read_until(b'\n', &mut self.raw)? == 0 {
            return Ok(false);
        }
        self.line_no += 1;
        while matches!(self.raw.last(), Some(b'\n' | b'\r')) {
            self.raw.pop();
        }
        let mut text = String::from_utf8_lossy(&self.raw);
        if self.line_no == 1 {
            if let Some(rest) = text.strip_prefix('\u{feff}') {
                text = rest.to_string().into();
            }
        }
        self.line.clear();
        self.line.push_str(&text);
        Ok(true)
    }

    /// Reads the next data row, skipping blank and comment lines.
    pub fn next_row(&mut self) -> std::io::Result<Next> {
        loop {
            if !self.next_line()? {
                return Ok(Next::End);
            }
            if is_skipped(&self.line) {
                continue;
            }
            let line = std::mem::take(&mut self.line);
            let r = self.split(&line);
            self.line = line;
            return Ok(match r {
                Ok(()) => Next::Row(self.line_no),
                Err(reason) => Next::Bad(self.line_no, reason),
            });
        }
    }

    /// The number of cells of the current row.
    pub fn width(&self) -> usize {
        self.cells.len()
    }

    /// The current row's cell `i` (0-based), unquoted and trimmed; "" past its end.
    pub fn cell(&self, i: usize) -> &str {
        self.cells
            .get(i)
            .map_or("", |&(a, b)| &self.cells_text[a..b])
    }

    fn split(&mut self, line: &str) -> Result<(), String> {
        self.cells_text.clear();
        self.cells.clear();
        let Some(d) = self.delimiter.char() else {
            for cell in line.split_whitespace() {
                let a = self.cells_text.len();
                self.cells_text.push_str(cell);
                self.cells.push((a, self.cells_text.len()));
            }
            return Ok(());
        };
        let blank = |c: char| c != d && (c == ' ' || c == '\t');
        let mut chars = line.chars().peekable();
        loop {
            while chars.next_if(|&c| blank(c)).is_some() {}
            let a = self.cells_text.len();
            if chars.next_if_eq(&'"').is_some() {
                loop {
                    match chars.next() {
                        None => {
                            return Err(format!(
                                "cell {} opens a quote that the line does not close",
                                self.cells.len() + 1
                            ))
                        }
                        Some('"') if chars.next_if_eq(&'"').is_some() => self.cells_text.push('"'),
                        Some('"') => break,
                        Some(c) => self.cells_text.push(c),
                    }
                }
                self.cells.push((a, self.cells_text.len()));
                while chars.next_if(|&c| blank(c)).is_some() {}
                match chars.next() {
                    None => return Ok(()),
                    Some(c) if c == d => {}
                    Some(c) => {
                        return Err(format!(
                            "cell {}: {c:?} after its closing quote",
                            self.cells.len()
                        ))
                    }
                }
            } else {
                let end = loop {
                    match chars.next() {
                        None => break true,
                        Some(c) if c == d => break false,
                        Some(c) => self.cells_text.push(c),
                    }
                };
                let kept = self.cells_text[a..].trim_end().len();
                self.cells_text.truncate(a + kept);
                self.cells.push((a, self.cells_text.len()));
                if end {
                    return Ok(());
                }
            }
        }
    }
}

/// A blank line or a `#` comment.
fn is_skipped(line: &str) -> bool {
    let t = line.trim_start();
    t.is_empty() || t.starts_with('#')
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rows(text: &str, d: Option<Delimiter>) -> (Vec<String>, Vec<Result<Vec<String>, String>>) {
        let mut t = Table::open(text.as_bytes(), d).unwrap();
        let mut out = vec![];
        loop {
            match t.next_row().unwrap() {
                Next::Row(_) => {
                    out.push(Ok((0..t.width()).map(|i| t.cell(i).to_string()).collect()))
                }
                Next::Bad(_, r) => out.push(Err(r)),
                Next::End => break,
            }
        }
        (t.header.clone(), out)
    }

    #[test]
    fn delimiters_are_detected_and_cells_split() {
        let (h, r) = rows(
            "\u{feff}# comment\n\nt,x, y \r\n1,2,3\n# c\n4,,\"5,5\"\n",
            None,
        );
        assert_eq!(h, ["t", "x", "y"]);
        assert_eq!(r[0].as_ref().unwrap(), &["1", "2", "3"]);
        assert_eq!(r[1].as_ref().unwrap(), &["4", "", "5,5"]);
        let (h, r) = rows("t;x\n1;2,5\n", None);
        assert_eq!(h, ["t", "x"]);
        assert_eq!(r[0].as_ref().unwrap(), &["1", "2,5"]);
        let (h, r) = rows("t\tx\n1\t\n", None);
        assert_eq!(h, ["t", "x"]);
        assert_eq!(r[0].as_ref().unwrap(), &["1", ""]);
        let (h, r) = rows("  t   x  y\n 1 2\t3\n", None);
        assert_eq!(h, ["t", "x", "y"]);
        assert_eq!(r[0].as_ref().unwrap(), &["1", "2", "3"]);
        // Forced: a comma file read as whitespace keeps the commas in its one cell.
        let (h, _) = rows("t,x\n", Some(Delimiter::Whitespace));
        assert_eq!(h, ["t,x"]);
        // Quotes: doubled inside, spaces around, errors for an unclosed one and text after.
        let (h, r) = rows("\"a \"\"b\"\"\" , c\n \"1\" ,2\n\"1,2\n\"1\"x,2\n", None);
        assert_eq!(h, ["a \"b\"", "c"]);
        assert_eq!(r[0].as_ref().unwrap(), &["1", "2"]);
        assert!(r[1].as_ref().unwrap_err().contains("does not close"));
        assert!(r[2]
            .as_ref()
            .unwrap_err()
            .contains("after its closing quote"));
        // A trailing delimiter is an empty last cell.
        let (_, r) = rows("a,b,\n1,2,\n", None);
        assert_eq!(r[0].as_ref().unwrap(), &["1", "2", ""]);
    }

    #[test]
    fn no_header() {
        assert!(matches!(
            Table::open("# only\n\n".as_bytes(), None),
            Err(OpenError::NoHeader)
        ));
        assert!(matches!(
            Table::open("\"a,b\n".as_bytes(), None),
            Err(OpenError::BadHeader { line: 1, .. })
        ));
    }
}
