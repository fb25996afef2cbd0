//! [`InlineText`]: an immutable string kept inline (no heap allocation) up to `N` bytes and in a
//! `Box<str>` beyond, so the short texts of G-code commands (`M106`, `SET_VELOCITY_LIMIT …`)
//! never allocate while unusual long ones (`EXCLUDE_OBJECT_DEFINE` polygons) still work.
//!
//! Invariant: the inline bytes `buf[..len]` are always a whole `&str` copied (or built through
//! [`TextBuilder`] from whole `&str` pieces), so they are valid UTF-8; reading them back checks it
//! anyway (no `unsafe`) and would give "" if it ever failed. `N` must be at most 255.

use std::fmt;
use std::ops::Deref;

/// A string stored inline up to `N` bytes (see the module docs).
#[derive(Clone)]
pub struct InlineText<const N: usize> {
    repr: Repr<N>,
}

#[derive(Clone)]
enum Repr<const N: usize> {
    Inline { len: u8, buf: [u8; N] },
    Heap(Box<str>),
}

impl<const N: usize> InlineText<N> {
    /// Longest text stored without allocating.
    pub const INLINE_CAPACITY: usize = if N < 256 { N } else { 255 };

    /// A copy of `s` (inline when it fits).
    pub fn new(s: &str) -> Self {
        let mut b = TextBuilder::<N>::new();
        b.push_str(s);
        b.finish()
    }

    /// The text.
    pub fn as_str(&self) -> &str {
        match &self.repr {
            Repr::Inline { len, buf } => std::str::from_utf8(&buf[..usize::from(*len)]).unwrap_or(""),
            Repr::Heap(s) => s,
        }
    }

    /// Whether the text is on the heap (longer than [`Self::INLINE_CAPACITY`]).
    pub fn is_heap(&self) -> bool {
        matches!(self.repr, Repr::Heap(_))
    }

    /// Upper-cases the ASCII letters in place.
    pub fn make_ascii_uppercase(&mut self) {
        match &mut self.repr {
            Repr::Inline { len, buf } => buf[..usize::from(*len)].make_ascii_uppercase(),
            Repr::Heap(s) => s.make_ascii_uppercase(),
        }
    }
}

impl<const N: usize> Default for InlineText<N> {
    fn default() -> Self {
        InlineText {
            repr: Repr::Inline { len: 0, buf: [0; N] },
        }
    }
}

impl<const N: usize> Deref for InlineText<N> {
    type Target = str;
    fn deref(&self) -> &str {
        self.as_str()
    }
}

impl<const N: usize> AsRef<str> for InlineText<N> {
    fn as_ref(&self) -> &str {
        self.as_str()
    }
}

impl<const N: usize> From<&str> for InlineText<N> {
    fn from(s: &str) -> Self {
        Self::new(s)
    }
}

impl<const N: usize> From<String> for InlineText<N> {
    fn from(s: String) -> Self {
        Self::new(&s)
    }
}

impl<const N: usize> fmt::Debug for InlineText<N> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        fmt::Debug::fmt(self.as_str(), f)
    }
}

impl<const N: usize> fmt::Display for InlineText<N> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl<const N: usize, const M: usize> PartialEq<InlineText<M>> for InlineText<N> {
    fn eq(&self, other: &InlineText<M>) -> bool {
        self.as_str() == other.as_str()
    }
}

impl<const N: usize> Eq for InlineText<N> {}

impl<const N: usize> std::hash::Hash for InlineText<N> {
    fn hash<H: std::hash::Hasher>(&self, state: &mut H) {
        self.as_str().hash(state)
    }
}

impl<const N: usize> PartialEq<str> for InlineText<N> {
    fn eq(&self, other: &str) -> bool {
        self.as_str() == other
    }
}

impl<const N: usize> PartialEq<&str> for InlineText<N> {
    fn eq(&self, other: &&str) -> bool {
        self.as_str() == *other
    }
}

impl<const N: usize> PartialEq<String> for InlineText<N> {
    fn eq(&self, other: &String) -> bool {
        self.as_str() == other.as_str()
    }
}

/// Builds an [`InlineText`] from pieces (also through `write!`); moves to the heap only when
/// the text outgrows the inline capacity.
#[derive(Debug)]
pub struct TextBuilder<const N: usize> {
    len: usize,
    buf: [u8; N],
    heap: Option<String>,
}

impl<const N: usize> TextBuilder<N> {
    pub fn new() -> Self {
        TextBuilder {
            len: 0,
            buf: [0; N],
            heap: None,
        }
    }

    /// Appends `s`.
    pub fn push_str(&mut self, s: &str) {
        if let Some(h) = &mut self.heap {
            h.push_str(s);
            return;
        }
        let end = self.len + s.len();
        if end <= InlineText::<N>::INLINE_CAPACITY {
            self.buf[self.len..end].copy_from_slice(s.as_bytes());
            self.len = end;
        } else {
            let mut h = String::with_capacity(end);
            h.push_str(std::str::from_utf8(&self.buf[..self.len]).unwrap_or(""));
            h.push_str(s);
            self.heap = Some(h);
        }
    }

    /// The text built.
    pub fn finish(self) -> InlineText<N> {
        let repr = match self.heap {
            Some(h) => Repr::Heap(h.into_boxed_str()),
            None => Repr::Inline {
                // `len` ≤ INLINE_CAPACITY ≤ 255.
                len: u8::try_from(self.len).unwrap_or(0),
                buf: self.buf,
            },
        };
        InlineText { repr }
    }
}

impl<const N: usize> Default for TextBuilder<N> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const N: usize> fmt::Write for TextBuilder<N> {
    fn write_str(&mut self, s: &str) -> fmt::Result {
        self.push_str(s);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::fmt::Write;

    #[test]
    fn short_text_is_inline_long_text_on_the_heap() {
        let t = InlineText::<8>::new("M106");
        assert_eq!(t, "M106");
        assert!(!t.is_heap());
        let t = InlineText::<8>::new("12345678");
        assert!(!t.is_heap());
        assert_eq!(t.as_str(), "12345678");
        let t = InlineText::<8>::new("123456789");
        assert!(t.is_heap());
        assert_eq!(t.as_str(), "123456789");
        assert_eq!(InlineText::<8>::default().as_str(), "");
    }

    #[test]
    fn builder_spills_to_the_heap_keeping_the_prefix() {
        let mut b = TextBuilder::<4>::new();
        write!(b, "G{}", 29).unwrap();
        b.push_str(".");
        assert_eq!(b.len, 4);
        b.push_str("12é");
        let t = b.finish();
        assert!(t.is_heap());
        assert_eq!(t, "G29.12é");
    }

    #[test]
    fn uppercase_in_place() {
        for s in ["set_velocity_limit", "a_very_long_lower_case_macro_name_é"] {
            let mut t = InlineText::<20>::new(s);
            t.make_ascii_uppercase();
            assert_eq!(t.as_str(), s.to_ascii_uppercase());
        }
    }

    #[test]
    fn capacity_is_at_most_255() {
        assert_eq!(InlineText::<300>::INLINE_CAPACITY, 255);
        let s = "x".repeat(256);
        let t = InlineText::<300>::new(&s);
        assert!(t.is_heap());
        assert_eq!(t.as_str(), s);
    }
}
