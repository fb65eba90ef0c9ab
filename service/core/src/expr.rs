//! A small arithmetic expression language for `custom` effects.
//!
//! Grammar: numbers, variables, `+ - * / ^` (with `^` right-associative), unary minus,
//! parentheses and the functions `sin cos tan asin acos atan atan2 sqrt abs sign exp ln log10
//! min max pow floor ceil`. Constants `pi` and `e`. Expressions are compiled once into a
//! postfix program over variable slots and evaluated on the hot path without allocation.

use std::fmt;

/// A compiled expression.
#[derive(Debug, Clone)]
pub struct Expr {
    ops: Vec<Op>,
    depth: usize,
    /// Variable names, by slot index used in [`Expr::eval`].
    pub vars: Vec<String>,
}

#[derive(Debug, Clone, Copy)]
enum Op {
    Num(f64),
    Var(usize),
    Neg,
    Add,
    Sub,
    Mul,
    Div,
    Pow,
    F1(fn(f64) -> f64),
    F2(fn(f64, f64) -> f64),
}

/// A parse error with its byte position.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub struct ExprError {
    /// Byte offset in the source.
    pub pos: usize,
    /// What is wrong.
    pub msg: String,
}

impl fmt::Display for ExprError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "at character {}: {}", self.pos + 1, self.msg)
    }
}

fn sign(x: f64) -> f64 {
    if x > 0.0 {
        1.0
    } else if x < 0.0 {
        -1.0
    } else {
        0.0
    }
}

fn func1(name: &str) -> Option<fn(f64) -> f64> {
    Some(match name {
        "sin" => f64::sin,
        "cos" => f64::cos,
        "tan" => f64::tan,
        "asin" => f64::asin,
        "acos" => f64::acos,
        "atan" => f64::atan,
        "sqrt" => f64::sqrt,
        "abs" => f64::abs,
        "sign" => sign,
        "exp" => f64::exp,
        "ln" => f64::ln,
        "log10" => f64::log10,
        "floor" => f64::floor,
        "ceil" => f64::ceil,
        _ => return None,
    })
}

fn func2(name: &str) -> Option<fn(f64, f64) -> f64> {
    Some(match name {
        "atan2" => f64::atan2,
        "min" => f64::min,
        "max" => f64::max,
        "pow" => f64::powf,
        _ => return None,
    })
}

struct Parser<'a> {
    s: &'a [u8],
    pos: usize,
    ops: Vec<Op>,
    vars: Vec<String>,
}

impl<'a> Parser<'a> {
    fn err<T>(&self, msg: impl Into<String>) -> Result<T, ExprError> {
        Err(ExprError {
            pos: self.pos,
            msg: msg.into(),
        })
    }
    fn ws(&mut self) {
        while self.pos < self.s.len() && self.s[self.pos].is_ascii_whitespace() {
            self.pos += 1;
        }
    }
    fn peek(&mut self) -> Option<u8> {
        self.ws();
        self.s.get(self.pos).copied()
    }
    fn eat(&mut self, c: u8) -> bool {
        if self.peek() == Some(c) {
            self.pos += 1;
            true
        } else {
            false
        }
    }
    fn expr(&mut self) -> Result<(), ExprError> {
        self.term()?;
        loop {
            if self.eat(b'+') {
                self.term()?;
                self.ops.push(Op::Add);
            } else if self.eat(b'-') {
                self.term()?;
                self.ops.push(Op::Sub);
            } else {
                return Ok(());
            }
        }
    }
    fn term(&mut self) -> Result<(), ExprError> {
        self.unary()?;
        loop {
            if self.eat(b'*') {
                self.unary()?;
                self.ops.push(Op::Mul);
            } else if self.eat(b'/') {
                self.unary()?;
                self.ops.push(Op::Div);
            } else {
                return Ok(());
            }
        }
    }
    fn unary(&mut self) -> Result<(), ExprError> {
        if self.eat(b'-') {
            self.unary()?;
            self.ops.push(Op::Neg);
            Ok(())
        } else if self.eat(b'+') {
            self.unary()
        } else {
            self.power()
        }
    }
    fn power(&mut self) -> Result<(), ExprError> {
        self.atom()?;
        if self.eat(b'^') {
            self.unary()?; // right-associative, allows 2^-1
            self.ops.push(Op::Pow);
        }
        Ok(())
    }
    fn atom(&mut self) -> Result<(), ExprError> {
        match self.peek() {
            None => self.err("expression ends too early"),
            Some(b'(') => {
                self.pos += 1;
                self.expr()?;
                if !self.eat(b')') {
                    return self.err("expected ')'");
                }
                Ok(())
            }
            Some(c) if c.is_ascii_digit() || c == b'.' => {
                let start = self.pos;
                while self.pos < self.s.len()
                    && (self.s[self.pos].is_ascii_digit() || self.s[self.pos] == b'.')
                {
                    self.pos += 1;
                }
                if self.pos < self.s.len() && (self.s[self.pos] == b'e' || self.s[self.pos] == b'E')
                {
                    let save = self.pos;
                    self.pos += 1;
                    if self.pos < self.s.len()
                        && (self.s[self.pos] == b'+' || self.s[self.pos] == b'-')
                    {
                        self.pos += 1;
                    }
                    if self.pos < self.s.len() && self.s[self.pos].is_ascii_digit() {
                        while self.pos < self.s.len() && self.s[self.pos].is_ascii_digit() {
                            self.pos += 1;
                        }
                    } else {
                        self.pos = save;
                    }
                }
                let text = std::str::from_utf8(&self.s[start..self.pos]).unwrap_or("");
                match text.parse::<f64>() {
                    Ok(v) => {
                        self.ops.push(Op::Num(v));
                        Ok(())
                    }
                    Err(_) => Err(ExprError {
                        pos: start,
                        msg: format!("bad number '{text}'"),
                    }),
                }
            }
            Some(c) if c.is_ascii_alphabetic() || c == b'_' => {
                let start = self.pos;
                while self.pos < self.s.len()
                    && (self.s[self.pos].is_ascii_alphanumeric() || self.s[self.pos] == b'_')
                {
                    self.pos += 1;
                }
                let name = std::str::from_utf8(&self.s[start..self.pos])
                    .unwrap_or("")
                    .to_string();
                if self.eat(b'(') {
                    self.expr()?;
                    let two = self.eat(b',');
                    if two {
                        self.expr()?;
                    }
                    if !self.eat(b')') {
                        return self.err("expected ')' after function arguments");
                    }
                    match (two, func1(&name), func2(&name)) {
                        (false, Some(f), _) => self.ops.push(Op::F1(f)),
                        (true, _, Some(f)) => self.ops.push(Op::F2(f)),
                        (_, None, None) => {
                            return Err(ExprError {
                                pos: start,
                                msg: format!("unknown function '{name}'"),
                            })
                        }
                        _ => {
                            return Err(ExprError {
                                pos: start,
                                msg: format!("wrong number of arguments to '{name}'"),
                            })
                        }
                    }
                    return Ok(());
                }
                match name.as_str() {
                    "pi" => self.ops.push(Op::Num(std::f64::consts::PI)),
                    "e" => self.ops.push(Op::Num(std::f64::consts::E)),
                    _ => {
                        let slot = match self.vars.iter().position(|v| *v == name) {
                            Some(i) => i,
                            None => {
                                self.vars.push(name);
                                self.vars.len() - 1
                            }
                        };
                        self.ops.push(Op::Var(slot));
                    }
                }
                Ok(())
            }
            Some(c) => self.err(format!("unexpected '{}'", c as char)),
        }
    }
}

impl Expr {
    /// Parses and compiles.
    pub fn parse(src: &str) -> Result<Expr, ExprError> {
        let mut p = Parser {
            s: src.as_bytes(),
            pos: 0,
            ops: vec![],
            vars: vec![],
        };
        p.expr()?;
        if p.peek().is_some() {
            return p.err("unexpected text after the expression");
        }
        // Stack depth.
        let (mut d, mut max) = (0usize, 0usize);
        for op in &p.ops {
            match op {
                Op::Num(_) | Op::Var(_) => d += 1,
                Op::Neg | Op::F1(_) => {}
                _ => d -= 1,
            }
            max = max.max(d);
        }
        Ok(Expr {
            ops: p.ops,
            depth: max,
            vars: p.vars,
        })
    }

    /// Evaluates with variable values by slot (`vars[i]` for `self.vars[i]`).
    pub fn eval(&self, vars: &[f64]) -> f64 {
        let mut stack = [0.0f64; 32];
        let mut heap;
        let st: &mut [f64] = if self.depth <= 32 {
            &mut stack
        } else {
            heap = vec![0.0; self.depth];
            &mut heap
        };
        let mut n = 0;
        for op in &self.ops {
            match *op {
                Op::Num(v) => {
                    st[n] = v;
                    n += 1;
                }
                Op::Var(i) => {
                    st[n] = vars[i];
                    n += 1;
                }
                Op::Neg => st[n - 1] = -st[n - 1],
                Op::F1(f) => st[n - 1] = f(st[n - 1]),
                op => {
                    let (a, b) = (st[n - 2], st[n - 1]);
                    n -= 1;
                    st[n - 1] = match op {
                        Op::Add => a + b,
                        Op::Sub => a - b,
                        Op::Mul => a * b,
                        Op::Div => a / b,
                        Op::Pow => a.powf(b),
                        Op::F2(f) => f(a, b),
                        _ => unreachable!("unary and leaf ops handled above"),
                    };
                }
            }
        }
        st[0]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ev(s: &str, vars: &[(&str, f64)]) -> f64 {
        let e = Expr::parse(s).unwrap();
        let v: Vec<f64> = e
            .vars
            .iter()
            .map(|n| vars.iter().find(|(k, _)| k == n).unwrap().1)
            .collect();
        e.eval(&v)
    }

    #[test]
    fn evaluates() {
        assert_eq!(ev("1 + 2 * 3", &[]), 7.0);
        assert_eq!(ev("(1 + 2) * 3", &[]), 9.0);
        assert_eq!(ev("2 ^ 3 ^ 2", &[]), 512.0);
        assert_eq!(ev("-2 ^ 2", &[]), -4.0);
        assert_eq!(ev("2 ^ -1", &[]), 0.5);
        assert_eq!(ev("1.5e3 + x", &[("x", 2.0)]), 1502.0);
        assert!((ev("sin(2*pi*x/4)", &[("x", 1.0)]) - 1.0).abs() < 1e-15);
        assert_eq!(ev("sign(vx) * max(1, 2)", &[("vx", -3.0)]), -2.0);
        assert_eq!(ev("atan2(0, -1)", &[]), std::f64::consts::PI);
        assert_eq!(ev("x*x - y", &[("x", 3.0), ("y", 1.0)]), 8.0);
    }

    #[test]
    fn errors_name_the_place() {
        for (s, needle) in [
            ("1 +", "ends"),
            ("foo(1)", "unknown function"),
            ("(1", "')'"),
            ("1 2", "after"),
            ("#", "unexpected"),
            ("min(1)", "arguments"),
        ] {
            let e = Expr::parse(s).unwrap_err();
            assert!(e.to_string().contains(needle), "{s}: {e}");
        }
    }
}
