//! The message framing of Klipper's API socket: JSON objects each ended by the byte 0x03
//! ([`Framer`] cuts a byte stream into messages, refusing one longer than [`MAX_MESSAGE`]
//! without its end), and a request's shape `{"id", "method", "params"}` ([`parse_request`]).

use serde_json::{Map, Value};

/// The byte that ends every message (ASCII ETX).
pub const ETX: u8 = 0x03;
/// The longest message accepted; a client that sends more without 0x03 is disconnected.
pub const MAX_MESSAGE: usize = 1 << 20;

/// Why a client's byte stream cannot be read on.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum FrameError {
    #[error("message longer than {MAX_MESSAGE} bytes without its 0x03 end")]
    TooLong,
}

/// Cuts a byte stream into messages at each 0x03; keeps the unfinished tail.
#[derive(Debug, Default)]
pub struct Framer {
    partial: Vec<u8>,
}

impl Framer {
    /// Appends `data` and moves each finished message (without its 0x03) into `out`.
    pub fn push(&mut self, data: &[u8], out: &mut Vec<Vec<u8>>) -> Result<(), FrameError> {
        let mut rest = data;
        while let Some(end) = rest.iter().position(|&b| b == ETX) {
            if self.partial.len() + end > MAX_MESSAGE {
                return Err(FrameError::TooLong);
            }
            self.partial.extend_from_slice(&rest[..end]);
            out.push(std::mem::take(&mut self.partial));
            rest = &rest[end + 1..];
        }
        if self.partial.len() + rest.len() > MAX_MESSAGE {
            return Err(FrameError::TooLong);
        }
        self.partial.extend_from_slice(rest);
        Ok(())
    }

    /// Bytes waiting for their 0x03.
    pub fn pending(&self) -> usize {
        self.partial.len()
    }
}

/// One request: `id` is echoed in the reply (a request without one gets no reply).
#[derive(Debug, Clone, PartialEq)]
pub struct Request {
    pub id: Option<Value>,
    pub method: String,
    pub params: Map<String, Value>,
}

/// Why a message is not a request (answered with an error carrying the id, when one was read).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum RequestError {
    #[error("message is not valid UTF-8 (byte {at})")]
    NotUtf8 { at: usize },
    #[error("message is not JSON: {0}")]
    Json(String),
    #[error("message is not a JSON object")]
    NotObject,
    #[error("request has no \"method\" string")]
    NoMethod,
    #[error("request \"params\" is not an object")]
    ParamsNotObject,
}

/// Reads one message as a request; on error also returns the id when the message had one.
pub fn parse_request(bytes: &[u8]) -> Result<Request, (Option<Value>, RequestError)> {
    let text =
        std::str::from_utf8(bytes).map_err(|e| (None, RequestError::NotUtf8 { at: e.valid_up_to() }))?;
    let value: Value = serde_json::from_str(text).map_err(|e| (None, RequestError::Json(e.to_string())))?;
    let Value::Object(mut obj) = value else {
        return Err((None, RequestError::NotObject));
    };
    let id = obj.remove("id");
    let method = match obj.remove("method") {
        Some(Value::String(m)) => m,
        _ => return Err((id, RequestError::NoMethod)),
    };
    let params = match obj.remove("params") {
        None | Some(Value::Null) => Map::new(),
        Some(Value::Object(p)) => p,
        Some(_) => return Err((id, RequestError::ParamsNotObject)),
    };
    Ok(Request { id, method, params })
}

/// A message ready to send: the JSON text and its 0x03.
pub fn encode(value: &Value) -> Vec<u8> {
    let mut bytes = serde_json::to_vec(value).unwrap_or_else(|e| {
        // A Value always serializes; keep the client informed if that ever changes.
        format!("{{\"error\":{{\"error\":\"WebRequestError\",\"message\":\"json encoding error: {e}\"}}}}")
            .into_bytes()
    });
    bytes.push(ETX);
    bytes
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn messages_split_at_etx_across_reads() {
        let mut f = Framer::default();
        let mut out = Vec::new();
        f.push(b"{\"a\":1}\x03{\"b\"", &mut out).unwrap();
        assert_eq!(out, vec![b"{\"a\":1}".to_vec()]);
        f.push(b":2}\x03", &mut out).unwrap();
        assert_eq!(out[1], b"{\"b\":2}".to_vec());
        assert_eq!(f.pending(), 0);
    }

    #[test]
    fn over_a_mebibyte_without_etx_is_refused() {
        let mut f = Framer::default();
        let mut out = Vec::new();
        let chunk = vec![b' '; 64 * 1024];
        let mut result = Ok(());
        for _ in 0..17 {
            result = f.push(&chunk, &mut out);
            if result.is_err() {
                break;
            }
        }
        assert_eq!(result, Err(FrameError::TooLong));
        assert!(out.is_empty());
    }

    #[test]
    fn requests_and_their_errors() {
        let r = parse_request(br#"{"id": 7, "method": "info", "params": {}}"#).unwrap();
        assert_eq!(r.id, Some(Value::from(7)));
        assert_eq!(r.method, "info");
        let (id, e) = parse_request(br#"{"id": "x", "params": {}}"#).unwrap_err();
        assert_eq!((id, e), (Some(Value::from("x")), RequestError::NoMethod));
        assert_eq!(
            parse_request(b"{\"id\":1,\xff}").unwrap_err().1,
            RequestError::NotUtf8 { at: 8 }
        );
        assert_eq!(parse_request(b"[1]").unwrap_err().1, RequestError::NotObject);
        assert!(matches!(
            parse_request(b"{").unwrap_err().1,
            RequestError::Json(_)
        ));
        assert_eq!(
            parse_request(br#"{"id":1,"method":"info","params":3}"#)
                .unwrap_err()
                .1,
            RequestError::ParamsNotObject
        );
    }

    proptest! {
        #[test]
        fn any_split_of_a_stream_gives_the_same_messages(
            msgs in proptest::collection::vec(proptest::collection::vec(any::<u8>().prop_filter("not ETX", |b| *b != ETX), 0..200), 0..8),
            cuts in proptest::collection::vec(0usize..2000, 0..6),
        ) {
            let mut stream = Vec::new();
            for m in &msgs {
                stream.extend_from_slice(m);
                stream.push(ETX);
            }
            let mut cuts: Vec<usize> = cuts.into_iter().map(|c| c.min(stream.len())).collect();
            cuts.sort_unstable();
            let mut f = Framer::default();
            let mut out = Vec::new();
            let mut at = 0;
            for c in cuts.into_iter().chain([stream.len()]) {
                f.push(&stream[at..c], &mut out).unwrap();
                at = c;
            }
            prop_assert_eq!(out, msgs);
            prop_assert_eq!(f.pending(), 0);
        }

        #[test]
        fn parsing_any_bytes_never_panics(bytes in proptest::collection::vec(any::<u8>(), 0..300)) {
            let _ = parse_request(&bytes);
        }

        #[test]
        fn any_method_and_id_round_trip(method in ".{0,40}", id in any::<i64>()) {
            let msg = serde_json::json!({"id": id, "method": method, "params": {"a": [1, 2]}});
            let bytes = encode(&msg);
            prop_assert_eq!(bytes.last(), Some(&ETX));
            let r = parse_request(&bytes[..bytes.len() - 1]).unwrap();
            prop_assert_eq!(r.method, method);
            prop_assert_eq!(r.id, Some(Value::from(id)));
        }
    }
}
