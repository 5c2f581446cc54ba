//! CDR (little-endian) encoding exactly as on the DDS wire and in rosbag2 MCAP files: a 4-byte
//! encapsulation header `00 01 00 00` followed by the CDR body.

use byteorder::LittleEndian;

/// Encapsulation header for CDR little-endian (RTPS representation identifier CDR_LE).
pub const CDR_LE_HEADER: [u8; 4] = [0x00, 0x01, 0x00, 0x00];

/// A message that could not be encoded or decoded.
#[derive(Debug, thiserror::Error)]
pub enum CdrError {
    #[error("CDR payload of {len} bytes is shorter than the 4-byte encapsulation header")]
    TooShort { len: usize },
    #[error("unsupported CDR encapsulation {0:02x?} (only little-endian CDR 00 01 is read)")]
    UnsupportedEncapsulation([u8; 2]),
    #[error("CDR: {0}")]
    Codec(#[from] cdr_encoding::Error),
}

/// Encode a message with its encapsulation header.
pub fn encode<T: serde::Serialize>(message: &T) -> Result<Vec<u8>, CdrError> {
    let mut out = Vec::with_capacity(64);
    out.extend_from_slice(&CDR_LE_HEADER);
    cdr_encoding::to_writer::<T, LittleEndian, _>(&mut out, message)?;
    Ok(out)
}

/// Decode a message that starts with its encapsulation header.
pub fn decode<T: serde::de::DeserializeOwned>(bytes: &[u8]) -> Result<T, CdrError> {
    if bytes.len() < 4 {
        return Err(CdrError::TooShort { len: bytes.len() });
    }
    if bytes[0..2] != CDR_LE_HEADER[0..2] {
        return Err(CdrError::UnsupportedEncapsulation([bytes[0], bytes[1]]));
    }
    let (value, _consumed) = cdr_encoding::from_bytes::<T, LittleEndian>(&bytes[4..])?;
    Ok(value)
}
