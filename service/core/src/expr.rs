//! A small arithmetic expression language for `custom` effects.
//!
//! Grammar: numbers, variables, `+ - * / ^` (with `^` right-associative), unary minus,
//! parentheses and the functions `sin cos tan asin acos atan atan2 sqrt abs sign exp ln log10
//! min max pow floor ceil`. Constants `pi` and `e`. Expressions are compiled once into a
//! postfix program over variable slots and evaluated on the hot path without allocation.
//!
//! Expressions arrive in calibration documents from the network, so the parser bounds what it
//! takes: at most [`MAX_LEN`] bytes of source and at most [`MAX_DEPTH`] levels of nesting.
//! Every construct the recursive-descent parser recurses into counts as a level: a
//! parenthesis, a function call, a unary sign and the right operand of `^` (so `2^2^2` is two
//! levels deep, `--x` two, `sin((x))` three). With the nesting bounded, so is the evaluation
//! stack of the compiled program ([`MAX_STACK`]); sums and products of any length are flat.

use std::fmt;

/// Longest expression source accepted, bytes.
pub const MAX_LEN: usize = 4096;

/// Deepest nesting accepted: parentheses, function calls, unary signs and `^` right operands,
/// each one level.
pub const MAX_DEPTH: usize = 64;

/// Bound on the evaluation stack of a compiled expression. Each nesting level holds at most
/// three pending operands (a sum's left side, a product's left side, and a power's base or a
/// two-argument function's first argument), so an expression within [`MAX_DEPTH`] needs at
/// most `3·(MAX_DEPTH + 1) + 1` slots; [`Expr::parse`] also checks this directly.
pub const MAX_STACK: usize = 3 * (MAX_DEPTH + 1) + 1;

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
    /// Current nesting level (see [`MAX_DEPTH`]).
    depth: usize,
}

impl<'a> Parser<'a> {
    /// Runs `f` one nesting level deeper, refusing to go past [`MAX_DEPTH`]. Every recursive
    /// path of the parser goes through here, which bounds the native stack it uses.
    fn nested(
        &mut self,
        f: impl FnOnce(&mut Self) -> Result<(), ExprError>,
    ) -> Result<(), ExprError> {
        if self.depth >= MAX_DEPTH {
            return self.err(format!(
                "nesting deeper than {MAX_DEPTH} levels (parentheses, function calls, unary \
                 signs and `^` chains each count)"
            ));
        }
        self.depth += 1;
        let r = f(self);
        self.depth -= 1;
        r
    }
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
            self.nested(Self::unary)?;
            self.ops.push(Op::Neg);
            Ok(())
        } else if self.eat(b'+') {
            self.nested(Self::unary)
        } else {
            self.power()
        }
    }
    fn power(&mut self) -> Result<(), ExprError> {
        self.atom()?;
        if self.eat(b'^') {
            self.nested(Self::unary)?; // right-associative, allows 2^-1
            self.ops.push(Op::Pow);
        }
        Ok(())
    }
    fn atom(&mut self) -> Result<(), ExprError> {
        match self.peek() {
            None => self.err("expression ends too early"),
            Some(b'(') => self.nested(|p| {
                p.pos += 1;
                p.expr()?;
                if !p.eat(b')') {
                    return p.err("expected ')'");
                }
                Ok(())
            }),
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
                    let mut two = false;
                    self.nested(|p| {
                        p.expr()?;
                        two = p.eat(b',');
                        if two {
                            p.expr()?;
                        }
                        if !p.eat(b')') {
                            return p.err("expected ')' after function arguments");
                        }
                        Ok(())
                    })?;
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
    ///
    /// Refuses sources longer than [`MAX_LEN`] bytes and nesting deeper than [`MAX_DEPTH`]
    /// levels, so neither parsing nor evaluation can exhaust the stack.
    pub fn parse(src: &str) -> Result<Expr, ExprError> {
        if src.len() > MAX_LEN {
            return Err(ExprError {
                pos: MAX_LEN,
                msg: format!(
                    "expression too long ({} bytes; at most {MAX_LEN} are accepted)",
                    src.len()
                ),
            });
        }
        let mut p = Parser {
            s: src.as_bytes(),
            pos: 0,
            ops: vec![],
            vars: vec![],
            depth: 0,
        };
        p.expr()?;
        if p.peek().is_some() {
            return p.err("unexpected text after the expression");
        }
        // Evaluation stack depth; the parser emits a well-formed postfix program (every
        // operator finds its operands), checked here rather than trusted by `eval`.
        let (mut d, mut max) = (0usize, 0usize);
        for op in &p.ops {
            match op {
                Op::Num(_) | Op::Var(_) => d += 1,
                Op::Neg | Op::F1(_) => {
                    if d < 1 {
                        return p.err("internal error: malformed program");
                    }
                }
                _ => {
                    if d < 2 {
                        return p.err("internal error: malformed program");
                    }
                    d -= 1;
                }
            }
            max = max.max(d);
        }
        if d != 1 {
            return p.err("internal error: malformed program");
        }
        if max > MAX_STACK {
            return p.err(format!(
                "expression needs {max} evaluation stack slots; at most {MAX_STACK} are accepted"
            ));
        }
        Ok(Expr {
            ops: p.ops,
            depth: max,
            vars: p.vars,
        })
    }

    /// Evaluates with variable values by slot (`vars[i]` for `self.vars[i]`; `vars` must have
    /// at least `self.vars.len()` values). Never allocates: the stack is bounded by
    /// [`MAX_STACK`].
    pub fn eval(&self, vars: &[f64]) -> f64 {
        let mut small = [0.0f64; 32];
        let mut big;
        let st: &mut [f64] = if self.depth <= small.len() {
            &mut small
        } else {
            big = [0.0f64; MAX_STACK];
            &mut big
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

    fn refused(s: &str, needle: &str) {
        match Expr::parse(s) {
            Ok(_) => panic!("accepted an expression of {} bytes", s.len()),
            Err(e) => assert!(e.to_string().contains(needle), "{e}"),
        }
    }

    const TOO_DEEP: &str = "nesting deeper than 64 levels";

    #[test]
    fn huge_inputs_are_refused_not_crashed() {
        // Each of these overflowed the stack before the limits.
        let n = 100_000;
        refused(&("-".repeat(n) + "1"), "too long");
        refused(&("+".repeat(n) + "1"), "too long");
        refused(&("(".repeat(n) + "1" + &")".repeat(n)), "too long");
        refused(&"(".repeat(n), "too long");
        refused(&("sin(".repeat(n) + "1" + &")".repeat(n)), "too long");
        refused(&("2^".repeat(10_000) + "2"), "too long");
        // Within the length limit the nesting limit refuses them.
        refused(&("-".repeat(4000) + "1"), TOO_DEEP);
        refused(&("(".repeat(2000) + "1" + &")".repeat(2000)), TOO_DEEP);
        refused(&"(".repeat(4096), TOO_DEEP);
        refused(&("2^".repeat(2000) + "2"), TOO_DEEP);
        refused(&("-(".repeat(1000) + "1" + &")".repeat(1000)), TOO_DEEP);
        refused(&("max(1,".repeat(500) + "1" + &")".repeat(500)), TOO_DEEP);
    }

    #[test]
    fn limits_are_exact() {
        let d = MAX_DEPTH;
        let ok = |s: String| {
            if let Err(e) = Expr::parse(&s) {
                panic!("{s}: {e}")
            }
            s
        };
        // Unary signs: 64 accepted, 65 refused.
        assert_eq!(ev(&ok("-".repeat(d) + "1"), &[]), 1.0);
        refused(&("-".repeat(d + 1) + "1"), TOO_DEEP);
        ok("+".repeat(d) + "x");
        refused(&("+".repeat(d + 1) + "x"), TOO_DEEP);
        // Parentheses.
        assert_eq!(
            ev(&ok("(".repeat(d) + "x" + &")".repeat(d)), &[("x", 3.0)]),
            3.0
        );
        refused(&("(".repeat(d + 1) + "x" + &")".repeat(d + 1)), TOO_DEEP);
        // Function calls.
        ok("abs(".repeat(d) + "1" + &")".repeat(d));
        refused(&("abs(".repeat(d + 1) + "1" + &")".repeat(d + 1)), TOO_DEEP);
        ok("min(1,".repeat(d) + "1" + &")".repeat(d));
        refused(
            &("min(1,".repeat(d + 1) + "1" + &")".repeat(d + 1)),
            TOO_DEEP,
        );
        // Right-associative `^` chains: 64 right operands.
        assert_eq!(ev(&ok("1^".repeat(d) + "1"), &[]), 1.0);
        refused(&("1^".repeat(d + 1) + "1"), TOO_DEEP);
        // Mixed: every kind counts.
        ok("-(".repeat(d / 2) + "1" + &")".repeat(d / 2));
        refused(&("-(".repeat(d / 2) + "-1" + &")".repeat(d / 2)), TOO_DEEP);
        // The refusal points at the construct that went one level too deep.
        let e = Expr::parse(&("-".repeat(d + 1) + "1")).unwrap_err();
        assert_eq!(e.pos, d + 1, "{e}");
        // Length: MAX_LEN bytes accepted, one more refused.
        let mut s = "1".to_string();
        while s.len() + 2 <= MAX_LEN {
            s.push_str("+1");
        }
        s.push_str(&" ".repeat(MAX_LEN - s.len()));
        assert_eq!(s.len(), MAX_LEN);
        assert_eq!(ev(&s, &[]), ((MAX_LEN - 1) / 2 + 1) as f64);
        s.push(' ');
        refused(&s, "too long");
    }

    #[test]
    fn long_flat_expressions_evaluate_on_a_small_stack() {
        // A sum of products of 4 096 bytes: flat, whatever its length.
        let mut s = String::from("x");
        while s.len() + 8 <= MAX_LEN {
            s.push_str(" + x*y*2");
        }
        let e = Expr::parse(&s).unwrap();
        assert!(e.depth <= 3, "{}", e.depth);
        let terms = (s.len() - 1) / 8;
        assert_eq!(e.eval(&[1.0, 3.0]), 1.0 + 6.0 * terms as f64);
    }

    #[test]
    fn the_deepest_accepted_expression_evaluates_within_the_stack_bound() {
        // Three pending operands per level (sum, product, power base), nested to the limit.
        let d = MAX_DEPTH;
        let mut s = String::new();
        for _ in 0..d / 2 {
            s.push_str("1 + 1 * 1 ^ (");
        }
        s.push_str("1 + 1 * 1");
        s.push_str(&")".repeat(d / 2));
        let e = Expr::parse(&s).unwrap();
        assert!(e.depth > 32 && e.depth <= MAX_STACK, "{}", e.depth);
        assert_eq!(e.eval(&[]), 2.0);
        let mut s = String::new();
        for _ in 0..d {
            s.push_str("1 + 1 * max(1, ");
        }
        s.push('1');
        s.push_str(&")".repeat(d));
        let e = Expr::parse(&s).unwrap();
        assert!(e.depth > 32 && e.depth <= MAX_STACK, "{}", e.depth);
        assert_eq!(e.eval(&[]), (d + 1) as f64);
    }

    #[test]
    fn a_calibration_with_a_hostile_expression_is_refused_naming_the_field() {
        use crate::calib::Calibration;
        use crate::effects::{custom, EffectConfig};
        use crate::sample::Axis;
        let doc = |bad: &str| {
            let mut c = Calibration::example("m1");
            let term = |expr: &str| custom::Term {
                axis: Axis::X,
                expr: expr.into(),
            };
            c.effects.push(EffectConfig::Custom(custom::Config {
                id: "fine".into(),
                dynamic: false,
                terms: vec![term("sin(2*pi*x/4)")],
                coefficients: vec![1e-3],
            }));
            c.effects.push(EffectConfig::Custom(custom::Config {
                id: "hostile".into(),
                dynamic: false,
                terms: vec![term("x"), term(bad)],
                coefficients: vec![0.0, 0.0],
            }));
            c.to_json()
        };
        let refusal = |bad: &str| {
            let c = Calibration::from_json(&doc(bad)).expect("well-formed JSON");
            match c.build() {
                Ok(_) => panic!("built a calibration with a {}-byte expression", bad.len()),
                Err(e) => e.to_string(),
            }
        };
        let field = "calibration field `effects[1].terms[1].expr`: ";
        let e = refusal(&("-".repeat(100_000) + "x"));
        assert!(e.starts_with(field) && e.contains("too long"), "{e}");
        let e = refusal(&("(".repeat(100_000) + "x" + &")".repeat(100_000)));
        assert!(e.starts_with(field) && e.contains("too long"), "{e}");
        let e = refusal(&("-".repeat(MAX_DEPTH + 1) + "x"));
        assert_eq!(
            e,
            format!(
                "{field}at character 66: nesting deeper than 64 levels (parentheses, function \
                 calls, unary signs and `^` chains each count)"
            )
        );
        let e = refusal(&("x^".repeat(1000) + "x"));
        assert!(e.starts_with(field) && e.contains(TOO_DEEP), "{e}");
        // At the limit the document builds.
        let ok = Calibration::from_json(&doc(&("-".repeat(MAX_DEPTH) + "x"))).unwrap();
        assert!(ok.build().is_ok());
    }
}
