//! `sensor_msgs` of ROS 2 Jazzy: the types of `ros2-interfaces-jazzy-serde`, except [`msg::Image`]
//! and [`msg::PointCloud2`]. Those two have the same fields, but their `data` (`uint8[]`: a 640×480
//! depth image is 614 kB, a birds-eye cloud up to 0.7 MB, each at 30 Hz) is (de)serialized as one
//! block instead of one serde call per byte. CDR encodes `sequence<octet>` the same either way (a
//! 4-byte aligned `uint32` length, then the bytes), so the wire format is unchanged; `patchwalk_ros::wire`'s tests
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
