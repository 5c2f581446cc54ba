//! What the nodes' restart checkpoints share: the bytes a consumer of `/gcode/moves`
//! acknowledges with (`GcodeAck.resume_state`), read back by the same node restarted.
//!
//! A checkpoint is a flat CDR struct led by three fields — its format, the first move it has
//! not finished, and a digest of the options that shaped its output — so a restarted node can
//! refuse, by name, a state that is not its own to continue: of another format, of another
//! point, or written with other options (which would continue another plan or other
//! commands). What its values must satisfy is each node's to check.

/// What leads every checkpoint (its first field: the CDR layout is that of the three fields
/// written flat).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct CheckpointHeader {
    pub format: u32,
    /// The first move not finished (the acknowledged point).
    pub next_sequence: u64,
    /// [`options_digest`] of the options of the node that wrote it.
    pub options_digest: u64,
}

/// A node's checkpoint type.
pub trait Checkpoint: serde::Serialize + serde::de::DeserializeOwned {
    /// The format this build writes and reads.
    const FORMAT: u32;
    /// Who writes it ("planner"), for messages.
    const WRITER: &'static str;
    /// What continuing from another writer's options would do, for messages.
    const OTHER_OPTIONS_WOULD: &'static str;
    fn header(&self) -> &CheckpointHeader;

    /// The header of a checkpoint of this type for the move `next_sequence`.
    fn header_for(next_sequence: u64, options_digest: u64) -> CheckpointHeader {
        CheckpointHeader {
            format: Self::FORMAT,
            next_sequence,
            options_digest,
        }
    }
}

/// Why acknowledged bytes are not a checkpoint this node can continue from.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ResumeStateError {
    #[error("resume state of {len} bytes is not a {writer} checkpoint: {reason}")]
    Malformed {
        writer: &'static str,
        len: usize,
        reason: String,
    },
    #[error("resume state has format {found}, this {writer} reads format {ours}")]
    Format {
        writer: &'static str,
        ours: u32,
        found: u32,
    },
    #[error("resume state is for move {found}, the resume point is move {expected}")]
    WrongPoint { expected: u64, found: u64 },
    #[error(
        "resume state was written by a {writer} with other options (digest {found:016x}, ours \
         {ours:016x}): {would}"
    )]
    OtherOptions {
        writer: &'static str,
        would: &'static str,
        ours: u64,
        found: u64,
    },
}

/// The bytes of `checkpoint` (plain numbers and flags: CDR encoding cannot fail).
pub fn to_bytes<C: Checkpoint>(checkpoint: &C) -> Vec<u8> {
    crate::cdr::encode(checkpoint).unwrap_or_default()
}

/// Read the checkpoint acknowledged at `resume_point` by a node whose options have
/// `options_digest`, refusing any other.
pub fn from_bytes<C: Checkpoint>(
    bytes: &[u8],
    resume_point: u64,
    options_digest: u64,
) -> Result<C, ResumeStateError> {
    let c: C = crate::cdr::decode(bytes).map_err(|e| ResumeStateError::Malformed {
        writer: C::WRITER,
        len: bytes.len(),
        reason: e.to_string(),
    })?;
    let header = *c.header();
    if header.format != C::FORMAT {
        return Err(ResumeStateError::Format {
            writer: C::WRITER,
            ours: C::FORMAT,
            found: header.format,
        });
    }
    if header.next_sequence != resume_point {
        return Err(ResumeStateError::WrongPoint {
            expected: resume_point,
            found: header.next_sequence,
        });
    }
    if header.options_digest != options_digest {
        return Err(ResumeStateError::OtherOptions {
            writer: C::WRITER,
            would: C::OTHER_OPTIONS_WOULD,
            ours: options_digest,
            found: header.options_digest,
        });
    }
    Ok(c)
}

/// How far a planner's published plan reaches: the fields that lead its checkpoint after the
/// header (`polar_planner::resume::Checkpoint`, whose tests hold it to this layout).
///
/// A machine reads it from the planner's acknowledgement in `/gcode/progress` to know where
/// the plan it must receive ends: the streamer's `finished` travels on another topic and
/// can overtake the last segments.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PlannerReach {
    /// Stamp of plan time 0 (ns): the first segment's stamp.
    pub plan_epoch_ns: i64,
    /// Plan time at the end of everything published (s).
    pub t_s: f64,
}

impl PlannerReach {
    /// Stamp of the end of everything published (as the planner stamps plan time).
    pub fn end_ns(&self) -> i64 {
        crate::Time::after(self.plan_epoch_ns, self.t_s).as_nanos()
    }
}

/// How far a screw driver's published commands reach: the fields that lead its checkpoint
/// after the header (`screw_driver::stream::Checkpoint`, whose tests hold it to this layout).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ScrewReach {
    pub has_base: bool,
    pub base_ns: i64,
    /// Stamp of the last command published.
    pub last_stamp_ns: i64,
    /// Number of the next command: every one before it is published.
    pub next_command: u64,
}

#[derive(serde::Deserialize)]
struct Lead<R> {
    header: CheckpointHeader,
    reach: R,
}

/// The header and the reach `R` that lead checkpoint `bytes` (`None`: too short, or not CDR).
/// The rest of the checkpoint is the writer's own business and is not read.
pub fn reach<R: serde::de::DeserializeOwned>(bytes: &[u8]) -> Option<(CheckpointHeader, R)> {
    let lead: Lead<R> = crate::cdr::decode(bytes).ok()?;
    Some((lead.header, lead.reach))
}

/// A digest of options (FNV-1a over their exact `Debug` text: every float printed so that it
/// reads back the same), stable across builds and platforms, unlike `std`'s hashers.
pub fn options_digest(debug_text: &str) -> u64 {
    debug_text.bytes().fold(0xcbf2_9ce4_8422_2325, |h, b| {
        (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, PartialEq, serde::Serialize, serde::Deserialize)]
    struct Sample {
        header: CheckpointHeader,
        value: f64,
    }

    /// The header is its three fields written flat, as before it was shared.
    #[derive(serde::Serialize)]
    struct Flat {
        format: u32,
        next_sequence: u64,
        options_digest: u64,
        value: f64,
    }

    impl Checkpoint for Sample {
        const FORMAT: u32 = 3;
        const WRITER: &'static str = "sampler";
        const OTHER_OPTIONS_WOULD: &'static str = "it would sample otherwise";
        fn header(&self) -> &CheckpointHeader {
            &self.header
        }
    }

    fn sample(format: u32) -> Vec<u8> {
        let bytes = to_bytes(&Sample {
            header: CheckpointHeader {
                format,
                ..Sample::header_for(12, 99)
            },
            value: 0.5,
        });
        let flat = Flat {
            format,
            next_sequence: 12,
            options_digest: 99,
            value: 0.5,
        };
        assert_eq!(bytes, crate::cdr::encode(&flat).unwrap());
        bytes
    }

    #[test]
    fn its_own_checkpoint_reads_back_and_others_are_refused_by_name() {
        let back: Sample = from_bytes(&sample(3), 12, 99).unwrap();
        assert_eq!(back.value, 0.5);
        let e = from_bytes::<Sample>(&sample(4), 12, 99).unwrap_err();
        assert_eq!(
            e.to_string(),
            "resume state has format 4, this sampler reads format 3"
        );
        let e = from_bytes::<Sample>(&sample(3), 13, 99).unwrap_err();
        assert_eq!(
            e,
            ResumeStateError::WrongPoint {
                expected: 13,
                found: 12
            }
        );
        let e = from_bytes::<Sample>(&sample(3), 12, 98).unwrap_err();
        assert!(
            e.to_string().ends_with(
                "written by a sampler with other options (digest 0000000000000063, ours \
                 0000000000000062): it would sample otherwise"
            ),
            "{e}"
        );
        let e = from_bytes::<Sample>(&sample(3)[..9], 12, 99).unwrap_err();
        assert!(e
            .to_string()
            .starts_with("resume state of 9 bytes is not a sampler checkpoint"));
    }

    #[test]
    fn a_reach_is_read_from_the_lead_of_a_longer_checkpoint() {
        #[derive(serde::Serialize)]
        struct Planner {
            header: CheckpointHeader,
            plan_epoch_ns: i64,
            t_s: f64,
            rest: [f64; 3],
        }
        let bytes = crate::cdr::encode(&Planner {
            header: Sample::header_for(5, 1),
            plan_epoch_ns: 1_000,
            t_s: 2.5,
            rest: [9.0; 3],
        })
        .unwrap();
        let (header, r) = reach::<PlannerReach>(&bytes).unwrap();
        assert_eq!(header.next_sequence, 5);
        assert_eq!(
            r,
            PlannerReach {
                plan_epoch_ns: 1_000,
                t_s: 2.5
            }
        );
        assert_eq!(r.end_ns(), 2_500_001_000);
        assert_eq!(reach::<PlannerReach>(&bytes[..20]), None);
        assert_eq!(reach::<PlannerReach>(&[]), None);
    }

    /// FNV-1a's published test vectors (the empty string and "a").
    #[test]
    fn options_digest_is_fnv_1a() {
        assert_eq!(options_digest(""), 0xcbf2_9ce4_8422_2325);
        assert_eq!(options_digest("a"), 0xaf63_dc4c_8601_ec8c);
    }
}
