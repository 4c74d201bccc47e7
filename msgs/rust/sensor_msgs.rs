//! `sensor_msgs` of ROS 2 Jazzy: the types of `ros2-interfaces-jazzy-serde`, except [`msg::Image`]
//! and [`msg::PointCloud2`]. Those two have the same fields, but their `data` (`uint8[]`: a 640×480
//! depth image is 614 kB, a birds-eye cloud up to 0.7 MB, each at 30 Hz) is (de)serialized as one
//! block instead of one serde call per byte. CDR encodes `sequence<octet>` the same either way (a
//! 4-byte aligned `uint32` length, then the bytes), so the wire format is unchanged; the tests below
//! check it against the upstream types.

pub use ros2_interfaces_jazzy_serde::sensor_msgs::*;

pub mod msg {
    pub use ros2_interfaces_jazzy_serde::sensor_msgs::msg::*;

    use crate::std_msgs::msg::Header;

    /// `sensor_msgs/msg/Image`.
    #[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
    pub struct Image {
        pub header: Header,
        pub height: u32,
        pub width: u32,
        pub encoding: String,
        pub is_bigendian: u8,
        /// Row length in bytes.
        pub step: u32,
        #[serde(with = "super::octets")]
        pub data: Vec<u8>,
    }

    impl ros2_client::Message for Image {}

    /// `sensor_msgs/msg/PointCloud2`.
    #[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
    pub struct PointCloud2 {
        pub header: Header,
        pub height: u32,
        pub width: u32,
        pub fields: Vec<PointField>,
        pub is_bigendian: bool,
        pub point_step: u32,
        pub row_step: u32,
        #[serde(with = "super::octets")]
        pub data: Vec<u8>,
        pub is_dense: bool,
    }

    impl ros2_client::Message for PointCloud2 {}
}

/// Serde for a `uint8[]` field as one block of bytes (`serialize_bytes` / `deserialize_byte_buf`);
/// formats without a byte type may hand the bytes as a sequence, which is accepted too.
mod octets {
    use serde::de::{Deserializer, SeqAccess, Visitor};
    use serde::Serializer;

    pub fn serialize<S: Serializer>(data: &[u8], serializer: S) -> Result<S::Ok, S::Error> {
        serializer.serialize_bytes(data)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(deserializer: D) -> Result<Vec<u8>, D::Error> {
        deserializer.deserialize_byte_buf(Octets)
    }

    struct Octets;

    impl<'de> Visitor<'de> for Octets {
        type Value = Vec<u8>;

        fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
            f.write_str("a sequence of bytes")
        }

        fn visit_bytes<E: serde::de::Error>(self, bytes: &[u8]) -> Result<Vec<u8>, E> {
            Ok(bytes.to_vec())
        }

        fn visit_byte_buf<E: serde::de::Error>(self, bytes: Vec<u8>) -> Result<Vec<u8>, E> {
            Ok(bytes)
        }

        fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Vec<u8>, A::Error> {
            // The hint comes from the input: a bounded reservation, the vector grows past it.
            let mut bytes = Vec::with_capacity(seq.size_hint().unwrap_or(0).min(1 << 20));
            while let Some(byte) = seq.next_element()? {
                bytes.push(byte);
            }
            Ok(bytes)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::msg::{Image, PointCloud2, PointField};
    use crate::std_msgs::msg::Header;
    use ros2_interfaces_jazzy_serde::sensor_msgs::msg as upstream;
    use rustdds::serialization::{to_writer_with_rep_id, CDRDeserializerAdapter};
    use rustdds::RepresentationIdentifier;

    fn cdr<T: serde::Serialize>(value: &T) -> Vec<u8> {
        let mut out = Vec::new();
        to_writer_with_rep_id(&mut out, value, RepresentationIdentifier::CDR_LE).unwrap();
        out
    }

    fn decode<T: serde::de::DeserializeOwned>(body: &[u8]) -> Result<T, String> {
        use rustdds::dds::adapters::no_key::{DefaultDecoder, DeserializerAdapter};
        <CDRDeserializerAdapter<T> as DeserializerAdapter<T>>::from_bytes_with(
            body,
            RepresentationIdentifier::CDR_LE,
            <CDRDeserializerAdapter<T> as DefaultDecoder<T>>::DECODER,
        )
        .map_err(|e| format!("{e:?}"))
    }

    fn header() -> Header {
        Header { stamp: crate::builtin_interfaces::msg::Time { sec: 7, nanosec: 9 }, frame_id: "camera".into() }
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
        assert_eq!(cdr(&ours), cdr(&theirs));
        assert_eq!(decode::<Image>(&cdr(&theirs)).unwrap(), ours);
        let back: upstream::Image = decode(&cdr(&ours)).unwrap();
        assert_eq!(back.data, ours.data);
        // A length beyond the payload is an error, not a panic or a short image.
        let mut truncated = cdr(&ours);
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
        assert_eq!(cdr(&ours), cdr(&theirs));
        assert_eq!(decode::<PointCloud2>(&cdr(&theirs)).unwrap(), ours);
        assert_eq!(decode::<upstream::PointCloud2>(&cdr(&ours)).unwrap(), theirs);
    }
}
