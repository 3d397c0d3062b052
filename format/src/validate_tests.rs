use super::*;

fn camera(projection: u8, yfov: f32, ymag: f32) -> CameraRecord {
    let mut to_world = [0.0; 12];
    (to_world[0], to_world[4], to_world[8]) = (1.0, 1.0, 1.0);
    CameraRecord {
        to_world,
        projection,
        yfov,
        ymag,
        ..bytemuck::Zeroable::zeroed()
    }
}

#[test]
fn a_camera_is_perspective_or_orthographic_with_the_fields_that_make_it() {
    assert!(check_camera(&camera(CameraRecord::PERSPECTIVE, 0.8, 0.0)).is_ok());
    assert!(check_camera(&camera(CameraRecord::ORTHOGRAPHIC, 0.0, 2.5)).is_ok());
    for (c, bad) in [
        (camera(2, 0.8, 0.0), "projection"),
        (camera(CameraRecord::PERSPECTIVE, 0.8, 1.0), "ymag"),
        (camera(CameraRecord::PERSPECTIVE, 0.0, 0.0), "yfov"),
        (camera(CameraRecord::ORTHOGRAPHIC, 0.8, 2.5), "yfov"),
        (camera(CameraRecord::ORTHOGRAPHIC, 0.0, 0.0), "ymag"),
        (
            camera(CameraRecord::ORTHOGRAPHIC, 0.0, f32::INFINITY),
            "ymag",
        ),
    ] {
        let e = check_camera(&c).unwrap_err();
        assert!(e.contains(bad), "{e}");
    }
}

#[test]
fn an_environment_is_one_map_or_one_sky_within_the_models_range() {
    let sky = EnvironmentRecord {
        kind: EnvironmentRecord::SKY,
        strength: 1.0,
        sun_elevation: 30.0,
        turbidity: 3.0,
        ground_albedo: 0.3,
        sun_strength: 1.0,
        ..bytemuck::Zeroable::zeroed()
    };
    let mut map = EnvironmentRecord {
        kind: EnvironmentRecord::MAP,
        strength: 1.0,
        ..bytemuck::Zeroable::zeroed()
    };
    map.path[..7].copy_from_slice(b"sky.hdr");
    assert!(check_environment(&[]).is_ok());
    assert!(check_environment(&[sky]).is_ok());
    assert!(check_environment(&[map]).is_ok());
    let mut past_end = map;
    past_end.path[9] = b'x';
    let mut not_utf8 = map;
    not_utf8.path[0] = 0xff;
    for (e, bad) in [
        (vec![sky, sky], "at most one"),
        (vec![EnvironmentRecord { kind: 3, ..sky }], "kind"),
        (
            vec![EnvironmentRecord {
                strength: -1.0,
                ..sky
            }],
            "strength",
        ),
        (
            vec![EnvironmentRecord {
                turbidity: 0.5,
                ..sky
            }],
            "sky",
        ),
        (
            vec![EnvironmentRecord {
                sun_elevation: f32::NAN,
                ..sky
            }],
            "sky",
        ),
        (
            vec![EnvironmentRecord {
                path: [0; 224],
                ..map
            }],
            "path",
        ),
        (vec![past_end], "path"),
        (vec![not_utf8], "path"),
    ] {
        let err = check_environment(&e).unwrap_err();
        assert!(err.contains(bad), "{err}");
    }
}
