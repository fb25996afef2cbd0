//! Klipper's variable-length integers.
//!
//! A 32-bit value goes out in 7-bit groups, most significant first, with bit 7 set on every
//! byte but the last. The first byte's bits 5 and 6 are read as a sign extension, so `n` bytes
//! carry the range `-2^(7n-2) ..= 3·2^(7n-2) - 1`: 1 byte for -32..=95, 2 for -4096..=12287,
//! 3 for -2^19..=3·2^19-1, 4 for -2^26..=3·2^26-1, else 5. Unsigned values are sent as their
//! 32-bit pattern read signed, so `u32::MAX` takes one byte (as -1).

/// Longest encoding of a 32-bit value.
pub const VLQ_MAX: usize = 5;

/// Bytes [`encode`] writes for `v` (for counting wire bytes without encoding).
#[inline]
pub fn encoded_len(v: u32) -> usize {
    let sv = v as i32 as i64;
    let mut n = 1;
    while n < VLQ_MAX {
        let half = 1i64 << (7 * n - 2);
        if sv >= -half && sv < 3 * half {
            break;
        }
        n += 1;
    }
    n
}

/// Encodes `v` into `out`, returning the number of bytes written, or `None` if `out` is short.
pub fn encode(v: u32, out: &mut [u8]) -> Option<usize> {
    let n = encoded_len(v);
    let dst = out.get_mut(..n)?;
    for (i, b) in dst.iter_mut().enumerate() {
        let shift = 7 * (n - 1 - i);
        let group = ((v as u64) >> shift) as u8 & 0x7F;
        *b = if i + 1 < n { group | 0x80 } else { group };
    }
    Some(n)
}

/// Decodes one value from the front of `data`: `(raw 32-bit value, bytes used)`, or `None`
/// when the bytes end before the value does or the value runs past 5 bytes.
pub fn decode(data: &[u8]) -> Option<(u32, usize)> {
    let first = *data.first()?;
    let mut v = (first & 0x7F) as u32;
    if first & 0x60 == 0x60 {
        v |= !0x1F; // sign-extend bits 5..6 of the first byte
    }
    let mut used = 1;
    let mut b = first;
    while b & 0x80 != 0 {
        if used >= VLQ_MAX {
            return None;
        }
        b = *data.get(used)?;
        v = (v << 7) | (b & 0x7F) as u32;
        used += 1;
    }
    Some((v, used))
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn len_of(v: i64) -> usize {
        let mut buf = [0u8; 5];
        let n = encode(v as u32, &mut buf).unwrap();
        assert_eq!(encoded_len(v as u32), n);
        n
    }

    #[test]
    fn lengths_at_boundaries() {
        assert_eq!(len_of(-32), 1);
        assert_eq!(len_of(95), 1);
        assert_eq!(len_of(96), 2);
        assert_eq!(len_of(-33), 2);
        assert_eq!(len_of(-4096), 2);
        assert_eq!(len_of(12287), 2);
        assert_eq!(len_of(12288), 3);
        assert_eq!(len_of(-(1 << 19)), 3);
        assert_eq!(len_of(3 * (1 << 19) - 1), 3);
        assert_eq!(len_of(3 * (1 << 26) - 1), 4);
        assert_eq!(len_of(3 * (1 << 26)), 5);
        assert_eq!(len_of(u32::MAX as i64), 1);
    }

    #[test]
    fn golden_bytes() {
        let enc = |v: u32| {
            let mut buf = [0u8; 5];
            let n = encode(v, &mut buf).unwrap();
            buf[..n].to_vec()
        };
        assert_eq!(enc(0), [0x00]);
        assert_eq!(enc(100), [0x80, 0x64]);
        assert_eq!(enc(-1i32 as u32), [0x7F]);
        assert_eq!(enc(40_000), [0x82, 0xB8, 0x40]);
    }

    #[test]
    fn truncated_and_overlong_inputs() {
        assert_eq!(decode(&[]), None);
        assert_eq!(decode(&[0x82, 0xB8]), None);
        assert_eq!(decode(&[0x80, 0x80, 0x80, 0x80, 0x80, 0x00]), None);
    }

    proptest! {
        #[test]
        fn round_trip(v in any::<u32>()) {
            let mut buf = [0u8; 5];
            let n = encode(v, &mut buf).unwrap();
            prop_assert_eq!(decode(&buf[..n]), Some((v, n)));
            prop_assert_eq!(encoded_len(v), n);
        }

        #[test]
        fn decode_never_panics(data in proptest::collection::vec(any::<u8>(), 0..8)) {
            let _ = decode(&data);
        }
    }
}
