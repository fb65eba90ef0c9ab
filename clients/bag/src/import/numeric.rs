//! A table of numbers by column name, for procedures that read a recording as a whole (a
//! drift recording: time, displacements, temperatures): the same table reader and number
//! rules as [`super::read`], every bad cell named by line and column and counted, and no
//! columns returned unless every cell of every asked column is a finite number.
use super::{number, ImportError, Options, RowError};
use crate::import::table::{Next, OpenError, Table};
use std::io::BufRead;

/// The asked columns of a table, in the asked order.
#[derive(Debug, Clone, PartialEq)]
pub struct Columns {
    /// The header's column names.
    pub header: Vec<String>,
    /// The file line of each data row.
    pub lines: Vec<usize>,
    /// Per asked column, a value per data row.
    pub values: Vec<Vec<f64>>,
}

/// The header's column names only.
pub fn header<R: BufRead>(
    input: R,
    file: &str,
    options: &Options,
) -> Result<Vec<String>, ImportError> {
    Ok(open(input, file, options)?.header.clone())
}

/// Opens a table up to its header row; the errors name the file.
pub(super) fn open<R: BufRead>(
    input: R,
    file: &str,
    options: &Options,
) -> Result<Table<R>, ImportError> {
    match Table::open(input, options.delimiter) {
        Ok(t) => Ok(t),
        Err(OpenError::Io(error)) => Err(ImportError::Io {
            file: file.to_string(),
            error,
        }),
        Err(OpenError::NoHeader) => Err(ImportError::NoHeader {
            file: file.to_string(),
        }),
        Err(OpenError::BadHeader { line, reason }) => Err(ImportError::Header {
            file: file.to_string(),
            errors: vec![RowError {
                line,
                column: None,
                message: reason,
            }],
            columns: vec![],
        }),
    }
}

/// Reads the columns `names` of the table `input` (named `file` in messages).
pub fn read_columns<R: BufRead>(
    input: R,
    file: &str,
    names: &[String],
    options: &Options,
) -> Result<Columns, ImportError> {
    let mut table = open(input, file, options)?;
    let header = table.header.clone();
    let mut index = vec![];
    let mut header_errors = vec![];
    for n in names {
        let hits: Vec<usize> = (0..header.len()).filter(|&i| header[i] == *n).collect();
        match hits.as_slice() {
            [i] => index.push(*i),
            [] => header_errors.push(RowError {
                line: table.header_line,
                column: None,
                message: format!("no column {}", number::shown(n)),
            }),
            [first, second, ..] => header_errors.push(RowError {
                line: table.header_line,
                column: Some((second + 1, n.clone())),
                message: format!("a duplicate column name (also column {})", first + 1),
            }),
        }
    }
    if !header_errors.is_empty() {
        return Err(ImportError::Header {
            file: file.to_string(),
            errors: header_errors,
            columns: header,
        });
    }
    let io = |error| ImportError::Io {
        file: file.to_string(),
        error,
    };
    let mut values = vec![vec![]; names.len()];
    let mut lines = vec![];
    let (mut rows, mut bad_rows, mut errors, mut more) = (0u64, 0u64, vec![], 0u64);
    loop {
        let (line, split) = match table.next_row().map_err(io)? {
            Next::End => break,
            Next::Row(l) => (l, None),
            Next::Bad(l, why) => (l, Some(why)),
        };
        rows += 1;
        let mut bad = vec![];
        if let Some(why) = split {
            bad.push(RowError {
                line,
                column: None,
                message: why,
            });
        } else {
            for (k, &i) in index.iter().enumerate() {
                let cell = table.cell(i);
                let v = if cell.is_empty() {
                    Err("empty: every row needs a number here".to_string())
                } else {
                    number::value(cell)
                };
                match v {
                    Ok(v) => values[k].push(v),
                    Err(message) => bad.push(RowError {
                        line,
                        column: Some((i + 1, header[i].clone())),
                        message,
                    }),
                }
            }
        }
        if !bad.is_empty() {
            bad_rows += 1;
            for e in bad {
                if errors.len() < options.max_errors {
                    errors.push(e);
                } else {
                    more += 1;
                }
            }
        } else {
            lines.push(line);
        }
    }
    if bad_rows > 0 {
        return Err(ImportError::Rows {
            file: file.to_string(),
            bad_rows,
            rows,
            errors,
            more,
        });
    }
    if rows == 0 {
        return Err(ImportError::NoSamples {
            file: file.to_string(),
            rows,
        });
    }
    Ok(Columns {
        header,
        lines,
        values,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(v: &[&str]) -> Vec<String> {
        v.iter().map(|s| s.to_string()).collect()
    }

    #[test]
    fn reads_the_asked_columns_and_names_every_bad_cell() {
        let t = "# a drift\ntime_s,a,b\n0,1.5,2\n15,1.6,3\n";
        let c = read_columns(
            t.as_bytes(),
            "d.csv",
            &names(&["b", "time_s"]),
            &Options::default(),
        )
        .unwrap();
        assert_eq!(c.values, vec![vec![2.0, 3.0], vec![0.0, 15.0]]);
        assert_eq!(c.lines, vec![3, 4]);
        let t = "time_s,a,b\n0,x,2\n15,1.6,\n30,1,1\n";
        let e = read_columns(
            t.as_bytes(),
            "d.csv",
            &names(&["a", "b"]),
            &Options::default(),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("2 bad row(s) of 3"), "{e}");
        assert!(
            e.contains("d.csv:2:2: column \"a\": \"x\" is not a number"),
            "{e}"
        );
        assert!(e.contains("d.csv:3:3: column \"b\": empty"), "{e}");
        let e = read_columns(
            "t,a\n1,2\n".as_bytes(),
            "d.csv",
            &names(&["z"]),
            &Options::default(),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("no column \"z\""), "{e}");
    }
}
