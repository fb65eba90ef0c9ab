//! A physical dimension as powers of mm, s and K: what the units table (`units`) and a custom
//! expression's dimension (`expr`) share.

/// A dimension: powers of mm, s and K.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Dim {
    /// Power of length, mm.
    pub mm: i8,
    /// Power of time, s.
    pub s: i8,
    /// Power of temperature, K.
    pub k: i8,
}

impl Dim {
    /// A pure number.
    pub const ONE: Dim = Dim { mm: 0, s: 0, k: 0 };
    /// A length, mm.
    pub const MM: Dim = Dim { mm: 1, s: 0, k: 0 };

    pub(crate) fn mul(self, o: Dim) -> Dim {
        Dim {
            mm: self.mm + o.mm,
            s: self.s + o.s,
            k: self.k + o.k,
        }
    }
    pub(crate) fn div(self, o: Dim) -> Dim {
        Dim {
            mm: self.mm - o.mm,
            s: self.s - o.s,
            k: self.k - o.k,
        }
    }
    pub(crate) fn pow(self, n: i8) -> Dim {
        Dim {
            mm: self.mm * n,
            s: self.s * n,
            k: self.k * n,
        }
    }

    /// `mm/s²`, `1/K`, `mm·K`, `1`.
    pub fn text(&self) -> String {
        let part = |sym: &str, p: i8| -> String {
            match p.abs() {
                1 => sym.to_string(),
                2 => format!("{sym}²"),
                3 => format!("{sym}³"),
                n => format!("{sym}^{n}"),
            }
        };
        let (mut num, mut den) = (vec![], vec![]);
        for (sym, p) in [("mm", self.mm), ("s", self.s), ("K", self.k)] {
            if p > 0 {
                num.push(part(sym, p));
            } else if p < 0 {
                den.push(part(sym, p));
            }
        }
        let n = if num.is_empty() {
            "1".to_string()
        } else {
            num.join("·")
        };
        if den.is_empty() {
            n
        } else {
            format!("{n}/{}", den.join("·"))
        }
    }
}
