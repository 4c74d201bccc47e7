//! Conversions of the step_executor's inputs: the mapper's birds-eye cloud. Patches and poses
//! convert through `patchwalk_ros::patch_msg`, shared with the mapper.

use nalgebra::Vector3;

use patchwalk_msgs::sensor_msgs::msg::{PointCloud2, PointField};

/// x, y, z of a `sensor_msgs/PointCloud2` with FLOAT32 x/y/z fields (little-endian), as the mapper
/// publishes its birds-eye cloud. A malformed cloud is an error naming what is wrong.
pub fn points_from_cloud(cloud: &PointCloud2) -> Result<Vec<Vector3<f64>>, String> {
    if cloud.is_bigendian {
        return Err("big-endian clouds are not supported".into());
    }
    let offset = |name: &str| -> Result<usize, String> {
        let field = cloud.fields.iter().find(|f| f.name == name).ok_or_else(|| format!("no field {name:?}"))?;
        if field.datatype != PointField::FLOAT32 {
            return Err(format!("field {name:?} has datatype {}, expected FLOAT32 (7)", field.datatype));
        }
        Ok(field.offset as usize)
    };
    let offsets = [offset("x")?, offset("y")?, offset("z")?];
    let step = cloud.point_step as usize;
    let count = (cloud.width as usize).saturating_mul(cloud.height as usize);
    if offsets.iter().any(|o| o + 4 > step) {
        return Err(format!("point_step {step} is smaller than the x/y/z fields"));
    }
    if cloud.data.len() < count.saturating_mul(step) {
        return Err(format!("{} data bytes for {count} points of {step} bytes", cloud.data.len()));
    }
    let read = |at: usize| cloud.data.get(at..at + 4).and_then(|b| b.try_into().ok()).map(|b: [u8; 4]| f64::from(f32::from_le_bytes(b)));
    Ok((0..count)
        .filter_map(|i| {
            let base = i * step;
            Some(Vector3::new(read(base + offsets[0])?, read(base + offsets[1])?, read(base + offsets[2])?))
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A cloud laid out as patch_mapper publishes it (x, y, z FLOAT32, 12-byte points), plus
    /// malformed ones.
    #[test]
    fn clouds_decode_and_malformed_ones_are_errors() {
        let field = |name: &str, offset: u32| PointField { name: name.into(), offset, datatype: PointField::FLOAT32, count: 1 };
        let points = [[0.5f32, -1.0, 2.0], [0.25, 0.0, -3.5]];
        let cloud = PointCloud2 {
            height: 1,
            width: 2,
            fields: vec![field("x", 0), field("y", 4), field("z", 8)],
            point_step: 12,
            row_step: 24,
            data: points.iter().flatten().flat_map(|v| v.to_le_bytes()).collect(),
            is_dense: true,
            ..Default::default()
        };
        let decoded = points_from_cloud(&cloud).unwrap();
        assert_eq!(decoded, vec![Vector3::new(0.5, -1.0, 2.0), Vector3::new(0.25, 0.0, -3.5)]);
        let short = PointCloud2 { data: cloud.data[..20].to_vec(), ..cloud.clone() };
        assert!(points_from_cloud(&short).unwrap_err().contains("data bytes"));
        let no_z = PointCloud2 { fields: cloud.fields[..2].to_vec(), ..cloud.clone() };
        assert!(points_from_cloud(&no_z).unwrap_err().contains("\"z\""));
        let mut doubles = cloud.clone();
        doubles.fields[1].datatype = PointField::FLOAT64;
        assert!(points_from_cloud(&doubles).unwrap_err().contains("FLOAT32"));
        let narrow = PointCloud2 { point_step: 8, ..cloud.clone() };
        assert!(points_from_cloud(&narrow).unwrap_err().contains("point_step"));
        assert!(points_from_cloud(&PointCloud2 { is_bigendian: true, ..cloud }).is_err());
    }
}
