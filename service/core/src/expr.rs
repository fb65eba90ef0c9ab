//! A small arithmetic expression language for `custom` effects.
//!
//! Grammar: numbers, variables, `+ - * / ^` (with `^` right-associative), unary minus,
//! parentheses and the functions `sin cos tan asin acos atan atan2 sqrt abs sign exp ln log10
//! min max pow floor ceil`. Constants `pi` and `e`. Expressions are compiled once into a
//! postfix program over variable slots ([`Expr`]); the hot path runs a [`Program`]: the
//! expressions of an effect compiled together, constants folded, common sub-expressions
//! computed once, the sine and cosine of one argument taken together, without allocation.
//!
//! Expressions arrive in calibration documents from the network, so the parser bounds what it
//! takes: at most [`MAX_LEN`] bytes of source and at most [`MAX_DEPTH`] levels of nesting.
//! Every construct the recursive-descent parser recurses into counts as a level: a
//! parenthesis, a function call, a unary sign and the right operand of `^` (so `2^2^2` is two
//! levels deep, `--x` two, `sin((x))` three). With the nesting bounded, so is the evaluation
//! stack of the compiled program ([`MAX_STACK`]); sums and products of any length are flat.

use std::collections::HashMap;
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
    F1(Func1),
    F2(Func2),
}

/// A one-argument function of the language (and negation).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
enum Func1 {
    Neg,
    Sin,
    Cos,
    Tan,
    Asin,
    Acos,
    Atan,
    Sqrt,
    Abs,
    Sign,
    Exp,
    Ln,
    Log10,
    Floor,
    Ceil,
}

impl Func1 {
    #[inline]
    fn apply(self, x: f64) -> f64 {
        match self {
            Func1::Neg => -x,
            Func1::Sin => crate::trig::sin(x),
            Func1::Cos => crate::trig::cos(x),
            Func1::Tan => x.tan(),
            Func1::Asin => x.asin(),
            Func1::Acos => x.acos(),
            Func1::Atan => x.atan(),
            Func1::Sqrt => x.sqrt(),
            Func1::Abs => x.abs(),
            Func1::Sign => sign(x),
            Func1::Exp => x.exp(),
            Func1::Ln => x.ln(),
            Func1::Log10 => x.log10(),
            Func1::Floor => x.floor(),
            Func1::Ceil => x.ceil(),
        }
    }
}

/// A two-argument operator or function of the language.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
enum Func2 {
    Add,
    Sub,
    Mul,
    Div,
    /// `^` and `pow`.
    Pow,
    Atan2,
    Min,
    Max,
}

impl Func2 {
    #[inline]
    fn apply(self, a: f64, b: f64) -> f64 {
        match self {
            Func2::Add => a + b,
            Func2::Sub => a - b,
            Func2::Mul => a * b,
            Func2::Div => a / b,
            Func2::Pow => a.powf(b),
            Func2::Atan2 => a.atan2(b),
            Func2::Min => a.min(b),
            Func2::Max => a.max(b),
        }
    }
}

impl Op {
    /// The operation of a two-operand op.
    fn binary(self) -> Option<Func2> {
        Some(match self {
            Op::Add => Func2::Add,
            Op::Sub => Func2::Sub,
            Op::Mul => Func2::Mul,
            Op::Div => Func2::Div,
            Op::Pow => Func2::Pow,
            Op::F2(f) => f,
            Op::Num(_) | Op::Var(_) | Op::Neg | Op::F1(_) => return None,
        })
    }
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

fn func1(name: &str) -> Option<Func1> {
    Some(match name {
        "sin" => Func1::Sin,
        "cos" => Func1::Cos,
        "tan" => Func1::Tan,
        "asin" => Func1::Asin,
        "acos" => Func1::Acos,
        "atan" => Func1::Atan,
        "sqrt" => Func1::Sqrt,
        "abs" => Func1::Abs,
        "sign" => Func1::Sign,
        "exp" => Func1::Exp,
        "ln" => Func1::Ln,
        "log10" => Func1::Log10,
        "floor" => Func1::Floor,
        "ceil" => Func1::Ceil,
        _ => return None,
    })
}

fn func2(name: &str) -> Option<Func2> {
    Some(match name {
        "atan2" => Func2::Atan2,
        "min" => Func2::Min,
        "max" => Func2::Max,
        "pow" => Func2::Pow,
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
                Op::F1(f) => st[n - 1] = f.apply(st[n - 1]),
                op => {
                    let (a, b) = (st[n - 2], st[n - 1]);
                    n -= 1;
                    st[n - 1] = op
                        .binary()
                        .expect("unary and leaf ops handled above")
                        .apply(a, b);
                }
            }
        }
        st[0]
    }
}

/// Several expressions compiled together into one straight-line program over registers, for
/// the hot path: constant sub-expressions are folded (`2*pi` is one number), each distinct
/// sub-expression is computed once for all the expressions (`sin(2*pi*x/4)` and
/// `cos(2*pi*x/4)` share `2*pi*x/4`), and the sine and cosine of one argument come from one
/// `sin_cos`. The values are those of [`Expr::eval`], bit for bit: the same operations on the
/// same operands, a folded constant computed as evaluation would compute it.
#[derive(Debug, Clone)]
pub struct Program {
    /// Registers: the inputs, then the constants, then one per step's result.
    n_inputs: usize,
    consts: Vec<f64>,
    steps: Vec<Step>,
    n_regs: usize,
    /// The register holding each expression's value.
    outputs: Vec<usize>,
    /// For a program of at most [`SMALL_REGISTERS`] registers: the register file an
    /// evaluation starts from, the constants in their registers and zeros elsewhere (one
    /// copy of a fixed size, instead of zeroing the file and copying the constants in).
    small_start: [f64; SMALL_REGISTERS],
}

/// One instruction: operand and destination registers. The arithmetic operators have their
/// own steps (one dispatch, not a step's and then a function's).
#[derive(Debug, Clone, Copy)]
enum Step {
    Add {
        a: usize,
        b: usize,
        dst: usize,
    },
    Sub {
        a: usize,
        b: usize,
        dst: usize,
    },
    Mul {
        a: usize,
        b: usize,
        dst: usize,
    },
    Div {
        a: usize,
        b: usize,
        dst: usize,
    },
    Unary {
        f: Func1,
        x: usize,
        dst: usize,
    },
    Binary {
        f: Func2,
        a: usize,
        b: usize,
        dst: usize,
    },
    SinCos {
        x: usize,
        sin: usize,
        cos: usize,
    },
}

/// A register file: a fixed array whose size is a power of two (a register index, below the
/// size, is taken modulo it: no bounds check), or a slice of any length (checked).
trait Registers {
    fn get(&self, i: usize) -> f64;
    fn set(&mut self, i: usize, v: f64);
}

impl<const N: usize> Registers for [f64; N] {
    #[inline(always)]
    fn get(&self, i: usize) -> f64 {
        self[i & (N - 1)]
    }
    #[inline(always)]
    fn set(&mut self, i: usize, v: f64) {
        self[i & (N - 1)] = v;
    }
}

impl Registers for [f64] {
    #[inline(always)]
    fn get(&self, i: usize) -> f64 {
        self[i]
    }
    #[inline(always)]
    fn set(&mut self, i: usize, v: f64) {
        self[i] = v;
    }
}

/// A node of the expressions' shared graph (operands are earlier nodes).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
enum Node {
    /// The constant's bits.
    Const(u64),
    Input(usize),
    Unary(Func1, usize),
    Binary(Func2, usize, usize),
}

/// 1/c when it is exact: c a power of two whose reciprocal is a normal number too.
fn exact_reciprocal(c: f64) -> Option<f64> {
    const MANTISSA: u64 = (1 << 52) - 1;
    let r = 1.0 / c;
    (c.is_normal() && r.is_normal() && c.to_bits() & MANTISSA == 0).then_some(r)
}

/// Registers a program evaluates in without allocating (a power of two, as each size below).
const STACK_REGISTERS: usize = 64;

/// Registers of the smaller register file, for programs of a few terms.
const SMALL_REGISTERS: usize = 16;

/// Registers of the smallest register file, for a program of one or two terms.
const TINY_REGISTERS: usize = 8;

// A register index is taken modulo the size of a fixed register file ([`Registers`]).
const _: () = assert!(
    TINY_REGISTERS.is_power_of_two()
        && SMALL_REGISTERS.is_power_of_two()
        && STACK_REGISTERS.is_power_of_two()
);

impl Program {
    /// Compiles `exprs` into one program over `n_inputs` inputs; each expression comes with
    /// the input index of each of its variable slots (`inputs[i]` for `expr.vars[i]`).
    pub fn compile(exprs: &[(&Expr, &[usize])], n_inputs: usize) -> Program {
        let mut nodes: Vec<Node> = vec![];
        let mut ids: HashMap<Node, usize> = HashMap::new();
        let mut intern = |n: Node, nodes: &mut Vec<Node>| {
            *ids.entry(n).or_insert_with(|| {
                nodes.push(n);
                nodes.len() - 1
            })
        };
        let constant = |nodes: &[Node], id: usize| match nodes[id] {
            Node::Const(bits) => Some(f64::from_bits(bits)),
            _ => None,
        };
        let mut outputs = vec![];
        for (e, inputs) in exprs {
            // The parser checked that every operator finds its operands.
            let mut st: Vec<usize> = vec![];
            for op in &e.ops {
                let node = match *op {
                    Op::Num(v) => Node::Const(v.to_bits()),
                    Op::Var(i) => Node::Input(inputs[i]),
                    Op::Neg | Op::F1(_) => {
                        let f = match *op {
                            Op::F1(f) => f,
                            _ => Func1::Neg,
                        };
                        let x = st.pop().expect("a checked program");
                        match constant(&nodes, x) {
                            Some(v) => Node::Const(f.apply(v).to_bits()),
                            None => Node::Unary(f, x),
                        }
                    }
                    op => {
                        let f = op.binary().expect("leaf and unary ops handled above");
                        let b = st.pop().expect("a checked program");
                        let a = st.pop().expect("a checked program");
                        match (constant(&nodes, a), constant(&nodes, b)) {
                            (Some(a), Some(b)) => Node::Const(f.apply(a, b).to_bits()),
                            // Division by a power of two: multiplication by its exact
                            // reciprocal (the same real number rounded once: the same bits).
                            (None, Some(c)) if f == Func2::Div => match exact_reciprocal(c) {
                                Some(r) => {
                                    let r = intern(Node::Const(r.to_bits()), &mut nodes);
                                    Node::Binary(Func2::Mul, a, r)
                                }
                                None => Node::Binary(f, a, b),
                            },
                            _ => Node::Binary(f, a, b),
                        }
                    }
                };
                st.push(intern(node, &mut nodes));
            }
            outputs.push(st.pop().expect("a checked program"));
        }
        // Only what an expression's value needs (folding leaves the folded operands behind).
        let mut live = vec![false; nodes.len()];
        for &o in &outputs {
            live[o] = true;
        }
        for id in (0..nodes.len()).rev() {
            if live[id] {
                match nodes[id] {
                    Node::Unary(_, x) => live[x] = true,
                    Node::Binary(_, a, b) => {
                        live[a] = true;
                        live[b] = true;
                    }
                    Node::Const(_) | Node::Input(_) => {}
                }
            }
        }
        let mut reg = vec![usize::MAX; nodes.len()];
        let mut consts = vec![];
        for (id, n) in nodes.iter().enumerate().filter(|(id, _)| live[*id]) {
            match *n {
                Node::Input(i) => reg[id] = i,
                Node::Const(bits) => {
                    reg[id] = n_inputs + consts.len();
                    consts.push(f64::from_bits(bits));
                }
                _ => {}
            }
        }
        let mut n_regs = n_inputs + consts.len();
        for id in 0..nodes.len() {
            if live[id] && matches!(nodes[id], Node::Unary(..) | Node::Binary(..)) {
                reg[id] = n_regs;
                n_regs += 1;
            }
        }
        let mut steps = vec![];
        let mut emitted = vec![false; nodes.len()];
        for id in (0..nodes.len()).filter(|id| live[*id]) {
            if emitted[id] {
                continue;
            }
            emitted[id] = true;
            match nodes[id] {
                Node::Unary(f @ (Func1::Sin | Func1::Cos), x) => {
                    let other = if f == Func1::Sin {
                        Func1::Cos
                    } else {
                        Func1::Sin
                    };
                    match ids.get(&Node::Unary(other, x)).filter(|o| live[**o]) {
                        Some(&o) => {
                            // Both at the first one's place: their argument is earlier.
                            emitted[o] = true;
                            let (sin, cos) = if f == Func1::Sin { (id, o) } else { (o, id) };
                            steps.push(Step::SinCos {
                                x: reg[x],
                                sin: reg[sin],
                                cos: reg[cos],
                            });
                        }
                        None => steps.push(Step::Unary {
                            f,
                            x: reg[x],
                            dst: reg[id],
                        }),
                    }
                }
                Node::Unary(f, x) => steps.push(Step::Unary {
                    f,
                    x: reg[x],
                    dst: reg[id],
                }),
                Node::Binary(f, a, b) => {
                    let (a, b, dst) = (reg[a], reg[b], reg[id]);
                    steps.push(match f {
                        Func2::Add => Step::Add { a, b, dst },
                        Func2::Sub => Step::Sub { a, b, dst },
                        Func2::Mul => Step::Mul { a, b, dst },
                        Func2::Div => Step::Div { a, b, dst },
                        f => Step::Binary { f, a, b, dst },
                    })
                }
                Node::Const(_) | Node::Input(_) => {}
            }
        }
        let mut small_start = [0.0; SMALL_REGISTERS];
        if n_regs <= SMALL_REGISTERS {
            small_start[n_inputs..n_inputs + consts.len()].copy_from_slice(&consts);
        }
        Program {
            n_inputs,
            consts,
            steps,
            n_regs,
            outputs: outputs.iter().map(|o| reg[*o]).collect(),
            small_start,
        }
    }

    /// Number of expressions.
    pub fn len(&self) -> usize {
        self.outputs.len()
    }

    /// Whether the program has no expression.
    pub fn is_empty(&self) -> bool {
        self.outputs.is_empty()
    }

    /// Evaluates every expression with `inputs` (at least the program's inputs) and hands
    /// each value, in expression order, to `out(index, value)`. Allocates only for programs
    /// of more than 64 registers.
    pub fn eval(&self, inputs: &[f64], out: impl FnMut(usize, f64)) {
        self.eval_with(|i| inputs[i], out);
    }

    /// [`Self::eval`] with input `i` given by `input(i)`, read into its register as the
    /// evaluation starts (the caller fills no array of inputs first).
    #[inline]
    pub fn eval_with(&self, input: impl Fn(usize) -> f64, out: impl FnMut(usize, f64)) {
        // The register file is zeroed on every evaluation: on the stack and no larger than
        // the program needs, for the usual few-term programs.
        if self.n_regs <= TINY_REGISTERS {
            let mut r = [0.0; TINY_REGISTERS];
            r.copy_from_slice(&self.small_start[..TINY_REGISTERS]);
            self.run(&mut r, input, out);
        } else if self.n_regs <= SMALL_REGISTERS {
            let mut r = self.small_start;
            self.run(&mut r, input, out);
        } else if self.n_regs <= STACK_REGISTERS {
            let mut r = [0.0; STACK_REGISTERS];
            self.with_consts(&mut r);
            self.run(&mut r, input, out);
        } else {
            let mut r = vec![0.0; self.n_regs];
            self.with_consts(&mut r);
            self.run(r.as_mut_slice(), input, out);
        }
    }

    /// Puts the constants in their registers of `r`.
    fn with_consts(&self, r: &mut [f64]) {
        r[self.n_inputs..self.n_inputs + self.consts.len()].copy_from_slice(&self.consts);
    }

    /// Runs the steps on the register file `r` (at least `n_regs` registers, the constants in
    /// their registers).
    #[inline(always)]
    fn run<R: Registers + ?Sized>(
        &self,
        r: &mut R,
        input: impl Fn(usize) -> f64,
        mut out: impl FnMut(usize, f64),
    ) {
        for i in 0..self.n_inputs {
            r.set(i, input(i));
        }
        for step in &self.steps {
            match *step {
                Step::Add { a, b, dst } => r.set(dst, r.get(a) + r.get(b)),
                Step::Sub { a, b, dst } => r.set(dst, r.get(a) - r.get(b)),
                Step::Mul { a, b, dst } => r.set(dst, r.get(a) * r.get(b)),
                Step::Div { a, b, dst } => r.set(dst, r.get(a) / r.get(b)),
                Step::Unary { f, x, dst } => r.set(dst, f.apply(r.get(x))),
                Step::Binary { f, a, b, dst } => r.set(dst, f.apply(r.get(a), r.get(b))),
                Step::SinCos { x, sin, cos } => {
                    let (s, c) = crate::trig::sin_cos(r.get(x));
                    r.set(sin, s);
                    r.set(cos, c);
                }
            }
        }
        for (i, &o) in self.outputs.iter().enumerate() {
            out(i, r.get(o));
        }
    }
}

impl Expr {
    /// The dimension of the expression, given each variable's (see the units table):
    /// constants take the dimension they are added to (`T_air - 20`); a trigonometric,
    /// exponential or logarithmic function gives a number (the constants in its argument carry
    /// the unit: `sin(2*pi*x/4)`, a period of 4 mm); `None` when quantities of different
    /// units are added or compared, a variable has no known unit, or a power is not a whole
    /// constant (a square root of a square is whole again).
    pub fn dimension(
        &self,
        unit_of: &dyn Fn(&str) -> Option<crate::dim::Dim>,
    ) -> Option<crate::dim::Dim> {
        use crate::dim::Dim;
        // (dimension, the constant value when the operand is a constant)
        let mut st: Vec<(Dim, Option<f64>)> = Vec::with_capacity(self.depth.max(4));
        let same = |a: (Dim, Option<f64>), b: (Dim, Option<f64>)| -> Option<Dim> {
            match (a.1, b.1) {
                (Some(_), _) => Some(b.0),
                (_, Some(_)) => Some(a.0),
                _ if a.0 == b.0 => Some(a.0),
                _ => None,
            }
        };
        let scale = |d: Dim, num: i32, den: i32| -> Option<Dim> {
            let f = |p: i8| -> Option<i8> {
                let v = p as i32 * num;
                (v % den == 0).then(|| (v / den) as i8)
            };
            Some(Dim {
                mm: f(d.mm)?,
                s: f(d.s)?,
                k: f(d.k)?,
            })
        };
        for op in &self.ops {
            let two = |f: Func2, a: (Dim, Option<f64>), b: (Dim, Option<f64>)| {
                let c = match (a.1, b.1) {
                    (Some(x), Some(y)) => Some(f.apply(x, y)),
                    _ => None,
                };
                let d = match f {
                    Func2::Add | Func2::Sub | Func2::Min | Func2::Max => same(a, b)?,
                    Func2::Mul => Dim {
                        mm: a.0.mm + b.0.mm,
                        s: a.0.s + b.0.s,
                        k: a.0.k + b.0.k,
                    },
                    Func2::Div => Dim {
                        mm: a.0.mm - b.0.mm,
                        s: a.0.s - b.0.s,
                        k: a.0.k - b.0.k,
                    },
                    Func2::Pow => {
                        if a.0 == Dim::ONE {
                            Dim::ONE
                        } else {
                            let e = b.1?;
                            let twice = (2.0 * e).round();
                            if (2.0 * e - twice).abs() > 1e-9 || twice.abs() > 16.0 {
                                return None;
                            }
                            scale(a.0, twice as i32, 2)?
                        }
                    }
                    Func2::Atan2 => {
                        same(a, b)?;
                        Dim::ONE
                    }
                };
                Some((d, c))
            };
            let v = match *op {
                Op::Num(x) => (Dim::ONE, Some(x)),
                Op::Var(i) => (unit_of(self.vars.get(i)?)?, None),
                Op::Neg => {
                    let a = st.pop()?;
                    (a.0, a.1.map(|x| -x))
                }
                Op::F1(f) => {
                    let a = st.pop()?;
                    let d = match f {
                        Func1::Neg | Func1::Abs | Func1::Floor | Func1::Ceil => a.0,
                        Func1::Sqrt => scale(a.0, 1, 2)?,
                        _ => Dim::ONE,
                    };
                    (d, a.1.map(|x| f.apply(x)))
                }
                Op::Add | Op::Sub | Op::Mul | Op::Div | Op::Pow | Op::F2(_) => {
                    let b = st.pop()?;
                    let a = st.pop()?;
                    let f = match *op {
                        Op::Add => Func2::Add,
                        Op::Sub => Func2::Sub,
                        Op::Mul => Func2::Mul,
                        Op::Div => Func2::Div,
                        Op::Pow => Func2::Pow,
                        Op::F2(f) => f,
                        _ => unreachable!("a two-operand op"),
                    };
                    two(f, a, b)?
                }
            };
            st.push(v);
        }
        (st.len() == 1).then(|| st[0].0)
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
    fn a_program_gives_the_interpreters_bits_and_shares_work() {
        let srcs = [
            "sin(2*pi*x/4)",
            "cos(2*pi*x/4)",
            "sign(vx) * (T - 20)",
            "-x^2 + 3*2 - pow(x, 2) + atan2(vx, x) * min(x, 1) / max(2, vx)",
            "sqrt(abs(x)) + exp(-x) + ln(2 + x*x) + log10(10) + floor(x) + ceil(vx)",
            "tan(x) + asin(0.5) + acos(0.25) + atan(vx) + 2^-1 + e",
            "sin(x) + cos(vx)",
            "1/0 + x",
        ];
        let exprs: Vec<Expr> = srcs.iter().map(|s| Expr::parse(s).unwrap()).collect();
        let names = ["x", "vx", "T"];
        let slots: Vec<Vec<usize>> = exprs
            .iter()
            .map(|e| {
                e.vars
                    .iter()
                    .map(|v| names.iter().position(|n| n == v).unwrap())
                    .collect()
            })
            .collect();
        let list: Vec<(&Expr, &[usize])> = exprs
            .iter()
            .zip(&slots)
            .map(|(e, s)| (e, s.as_slice()))
            .collect();
        let p = Program::compile(&list, names.len());
        assert_eq!(p.len(), srcs.len());
        // 2*pi is folded, 2*pi*x/4 computed once, its sine and cosine by one sin_cos.
        let sincos = |p: &Program| {
            p.steps
                .iter()
                .filter(|s| matches!(s, Step::SinCos { .. }))
                .count()
        };
        assert_eq!(sincos(&p), 1);
        let two = Program::compile(&list[..2], names.len());
        assert_eq!(two.steps.len(), 3, "{:?}", two.steps); // ·x, /4, sin_cos
                                                           // A long Horner chain: more registers than the register file on the stack holds.
        let horner = (1..=40).fold("x".to_string(), |acc, k| format!("({acc} + {k}) * vx"));
        let long = Expr::parse(&horner).unwrap();
        let long_slots: Vec<usize> = long
            .vars
            .iter()
            .map(|v| names.iter().position(|n| n == v).unwrap())
            .collect();
        let long_list = [(&long, long_slots.as_slice())];
        let big = Program::compile(&long_list, names.len());
        // One term over the first input alone: the smallest register file.
        let tiny = Program::compile(&list[..1], 1);
        assert!(tiny.n_regs <= TINY_REGISTERS);
        assert!(big.n_regs > STACK_REGISTERS);
        assert!((TINY_REGISTERS + 1..=SMALL_REGISTERS).contains(&two.n_regs));
        assert!((SMALL_REGISTERS + 1..=STACK_REGISTERS).contains(&p.n_regs));
        for ((p, list), inputs) in [
            (&p, &list[..]),
            (&two, &list[..2]),
            (&tiny, &list[..1]),
            (&big, &long_list[..]),
        ]
        .into_iter()
        .flat_map(|p| [[0.7, -3.0, 22.5], [-1.3, 0.0, 19.0], [1e3, 5.0, f64::NAN]].map(|i| (p, i)))
        {
            let mut got = vec![];
            p.eval(&inputs, |i, v| got.push((i, v)));
            assert_eq!(got.len(), list.len());
            for (i, (e, s)) in list.iter().enumerate() {
                let vars: Vec<f64> = s.iter().map(|k| inputs[*k]).collect();
                let want = e.eval(&vars);
                assert_eq!(got[i].0, i);
                assert_eq!(
                    got[i].1.to_bits(),
                    want.to_bits(),
                    "expression {i} of {}: {inputs:?}",
                    list.len()
                );
            }
        }
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
