//! A message or service request as it arrives on the wire: the serialized payload of a DDS DATA
//! submessage (a 4-byte encapsulation header — the representation identifier and two option bytes —
//! then the CDR body), decoded as rustdds decodes it for ros2-client's subscriptions and servers
//! (the same `supported_encodings` check, the same `CDRDeserializerAdapter`). [`encode`] writes the
//! header and body a little-endian publisher sends; tests and fuzz seeds are made with it.

use rustdds::dds::adapters::no_key::{DefaultDecoder, DeserializerAdapter};
use rustdds::serialization::{to_writer_with_rep_id, CDRDeserializerAdapter};
use rustdds::RepresentationIdentifier;
use serde::de::DeserializeOwned;
use serde::Serialize;

/// Length of the encapsulation header in front of the CDR body.
pub const HEADER_LEN: usize = 4;

/// Why a payload could not be decoded.
#[derive(Debug, thiserror::Error)]
pub enum WireError {
    #[error("payload of {len} bytes is shorter than the {HEADER_LEN}-byte encapsulation header")]
    TooShort { len: usize },
    #[error("representation identifier {0:02x?} is not one the CDR decoder supports")]
    Representation([u8; 2]),
    #[error("CDR body does not decode as {type_name}: {reason}")]
    Cdr { type_name: &'static str, reason: String },
}

/// Decode a serialized payload (header + CDR body) as `T`, exactly as the nodes' readers do.
pub fn decode<T: DeserializeOwned>(payload: &[u8]) -> Result<T, WireError> {
    let (Some(header), Some(body)) = (payload.get(..2), payload.get(HEADER_LEN..)) else {
        return Err(WireError::TooShort { len: payload.len() });
    };
    let representation = RepresentationIdentifier::from_bytes(header).map_err(|_| WireError::TooShort { len: payload.len() })?;
    let supported = <CDRDeserializerAdapter<T> as DeserializerAdapter<T>>::supported_encodings();
    if !supported.contains(&representation) {
        return Err(WireError::Representation(representation.to_bytes()));
    }
    <CDRDeserializerAdapter<T> as DeserializerAdapter<T>>::from_bytes_with(
        body,
        representation,
        <CDRDeserializerAdapter<T> as DefaultDecoder<T>>::DECODER,
    )
    .map_err(|e| WireError::Cdr { type_name: std::any::type_name::<T>(), reason: e.to_string() })
}

/// `value` as a little-endian publisher sends it: the `CDR_LE` header (no options) and the body.
pub fn encode<T: Serialize>(value: &T) -> Result<Vec<u8>, WireError> {
    let mut payload = RepresentationIdentifier::CDR_LE.to_bytes().to_vec();
    payload.extend_from_slice(&[0, 0]);
    to_writer_with_rep_id(&mut payload, value, RepresentationIdentifier::CDR_LE)
        .map_err(|e| WireError::Cdr { type_name: std::any::type_name::<T>(), reason: e.to_string() })?;
    Ok(payload)
}

#[cfg(test)]
mod tests {
    use super::*;
    use patchwalk_msgs::msg::PatchArray;
    use patchwalk_msgs::sensor_msgs::msg::{Image, PointCloud2, PointField};
    use patchwalk_msgs::std_msgs::msg::Header;
    use ros2_interfaces_jazzy_serde::sensor_msgs::msg as upstream;

    fn header() -> Header {
        Header { stamp: patchwalk_msgs::builtin_interfaces::msg::Time { sec: 7, nanosec: 9 }, frame_id: "camera".into() }
    }

    #[test]
    fn encoded_messages_decode_to_themselves() {
        let image = Image { height: 2, width: 3, encoding: "16UC1".into(), step: 6, data: vec![1; 12], ..Default::default() };
        let payload = encode(&image).unwrap();
        assert_eq!(&payload[..4], &[0x00, 0x01, 0, 0]);
        assert_eq!(decode::<Image>(&payload).unwrap(), image);
        let map = PatchArray::default();
        assert_eq!(decode::<PatchArray>(&encode(&map).unwrap()).unwrap(), map);
    }

    #[test]
    fn short_unknown_and_truncated_payloads_are_errors() {
        assert!(matches!(decode::<Image>(&[0x00, 0x01, 0]), Err(WireError::TooShort { len: 3 })));
        assert!(matches!(decode::<Image>(&[0x00, 0x20, 0, 0, 1, 2]), Err(WireError::Representation([0x00, 0x20]))));
        let mut payload = encode(&Image { encoding: "32FC1".into(), data: vec![0; 64], ..Default::default() }).unwrap();
        payload.truncate(payload.len() - 10);
        let err = decode::<Image>(&payload).unwrap_err();
        assert!(err.to_string().contains("Image"), "{err}");
    }

    #[test]
    fn an_image_has_the_upstream_wire_format_both_ways() {
        // An odd-length encoding string puts `data` behind padding: the alignment must match too.
        let data: Vec<u8> = (0..1203u32).map(|i| (i * 31 % 251) as u8).collect();
        let ours = Image { header: header(), height: 3, width: 401, encoding: "mono8".into(), is_bigendian: 1, step: 401, data };
        let theirs = upstream::Image {
            header: ours.header.clone(),
            height: ours.height,
            width: ours.width,
            encoding: ours.encoding.clone(),
            is_bigendian: ours.is_bigendian,
            step: ours.step,
            data: ours.data.clone(),
        };
        assert_eq!(encode(&ours).unwrap(), encode(&theirs).unwrap());
        assert_eq!(decode::<Image>(&encode(&theirs).unwrap()).unwrap(), ours);
        let back: upstream::Image = decode(&encode(&ours).unwrap()).unwrap();
        assert_eq!(back.data, ours.data);
        // A length beyond the payload is an error, not a panic or a short image.
        let mut truncated = encode(&ours).unwrap();
        truncated.truncate(truncated.len() - 10);
        assert!(decode::<Image>(&truncated).is_err());
    }

    #[test]
    fn a_point_cloud_has_the_upstream_wire_format_both_ways() {
        let field = |name: &str, offset: u32| PointField { name: name.into(), offset, datatype: PointField::FLOAT32, count: 1 };
        let data: Vec<u8> = [0.5f32, -1.25, 3.0, 7.5, 0.0, -2.0].iter().flat_map(|v| v.to_le_bytes()).collect();
        let ours = PointCloud2 {
            header: header(),
            height: 1,
            width: 2,
            fields: vec![field("x", 0), field("y", 4), field("z", 8)],
            is_bigendian: false,
            point_step: 12,
            row_step: 24,
            data,
            is_dense: true,
        };
        let theirs = upstream::PointCloud2 {
            header: ours.header.clone(),
            height: ours.height,
            width: ours.width,
            fields: ours.fields.clone(),
            is_bigendian: ours.is_bigendian,
            point_step: ours.point_step,
            row_step: ours.row_step,
            data: ours.data.clone(),
            is_dense: ours.is_dense,
        };
        assert_eq!(encode(&ours).unwrap(), encode(&theirs).unwrap());
        assert_eq!(decode::<PointCloud2>(&encode(&theirs).unwrap()).unwrap(), ours);
        assert_eq!(decode::<upstream::PointCloud2>(&encode(&ours).unwrap()).unwrap(), theirs);
    }
}
