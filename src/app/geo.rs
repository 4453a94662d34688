//! Where a world point is on the map, for the viewer's panel and its go-to: world
//! `(x, z)` to the file's CRS (sample `(i, j)` is at `origin + (i, j) * step`, SPEC section
//! 9) and on to latitude and longitude on WGS 84 through PROJ (GDAL's OSR), and back.

use crate::lod::heightfield::{Georef, Spacing};
use gdal::spatial_ref::{AxisMappingStrategy, CoordTransform, SpatialRef};

/// The map frame of one terrain.
pub struct Geo {
    georef: Georef,
    spacing: Spacing,
    /// CRS to WGS 84 and back; `None` for a geographic CRS (its coordinates are already
    /// longitude and latitude) or when PROJ cannot transform it.
    to_wgs84: Option<(CoordTransform, CoordTransform)>,
}

impl Geo {
    /// The frame of a georeferenced terrain; `None` when the file said nothing about
    /// where it is.
    pub fn new(georef: &Georef, spacing: Spacing) -> Option<Geo> {
        if georef.step == [0.0; 2] {
            return None;
        }
        let to_wgs84 = if georef.geographic || georef.wkt.is_empty() {
            None
        } else {
            (|| {
                let mut crs = SpatialRef::from_wkt(&georef.wkt).ok()?;
                let mut wgs = SpatialRef::from_epsg(4326).ok()?;
                for s in [&mut crs, &mut wgs] {
                    s.set_axis_mapping_strategy(AxisMappingStrategy::TraditionalGisOrder);
                }
                Some((CoordTransform::new(&crs, &wgs).ok()?, CoordTransform::new(&wgs, &crs).ok()?))
            })()
        };
        Some(Geo { georef: georef.clone(), spacing, to_wgs84 })
    }

    /// CRS coordinates of world `(x, z)`.
    pub fn world_to_crs(&self, x: f32, z: f32) -> [f64; 2] {
        let g = &self.georef;
        [
            g.origin[0] + x as f64 / self.spacing.x as f64 * g.step[0],
            g.origin[1] + z as f64 / self.spacing.z as f64 * g.step[1],
        ]
    }

    /// World `(x, z)` of CRS coordinates.
    pub fn crs_to_world(&self, c: [f64; 2]) -> (f32, f32) {
        let g = &self.georef;
        (
            ((c[0] - g.origin[0]) / g.step[0] * self.spacing.x as f64) as f32,
            ((c[1] - g.origin[1]) / g.step[1] * self.spacing.z as f64) as f32,
        )
    }

    /// Latitude and longitude (degrees, WGS 84 or the file's own geographic CRS).
    pub fn lat_lon(&self, x: f32, z: f32) -> Option<[f64; 2]> {
        let [e, n] = self.world_to_crs(x, z);
        if self.georef.geographic {
            return Some([n, e]);
        }
        let (to, _) = self.to_wgs84.as_ref()?;
        let (mut xs, mut ys) = ([e], [n]);
        to.transform_coords(&mut xs, &mut ys, &mut []).ok()?;
        Some([ys[0], xs[0]])
    }

    /// World `(x, z)` of a latitude and longitude.
    pub fn world_of(&self, lat: f64, lon: f64) -> Option<(f32, f32)> {
        if self.georef.geographic {
            return Some(self.crs_to_world([lon, lat]));
        }
        let (_, from) = self.to_wgs84.as_ref()?;
        let (mut xs, mut ys) = ([lon], [lat]);
        from.transform_coords(&mut xs, &mut ys, &mut []).ok()?;
        Some(self.crs_to_world([xs[0], ys[0]]))
    }

    /// World `(x, z)` of a latitude and longitude on a terrain of `extent` world units, or
    /// why not (off the terrain, with the corners it spans; or outside what the CRS maps):
    /// a go-to elsewhere would put the camera over nothing, silently.
    pub fn world_on_terrain(&self, lat: f64, lon: f64, extent: (f32, f32)) -> Result<(f32, f32), String> {
        let asked = format_lat_lon(lat, lon);
        let spans = match (self.lat_lon(0.0, 0.0), self.lat_lon(extent.0, extent.1)) {
            (Some(a), Some(b)) => {
                format!(" (it spans {} to {})", format_lat_lon(a[0], a[1]), format_lat_lon(b[0], b[1]))
            }
            _ => String::new(),
        };
        let Some((x, z)) = self.world_of(lat, lon) else {
            return Err(format!("{asked}: cannot be placed in the terrain's CRS ({}){spans}", self.crs()));
        };
        let on = |v: f32, side: f32| v.is_finite() && (0.0..=side).contains(&v);
        if !(on(x, extent.0) && on(z, extent.1)) {
            return Err(format!("{asked}: off the terrain{spans}"));
        }
        Ok((x, z))
    }

    /// "46.85120 N, 121.76031 W", then the projected coordinates for a projected CRS.
    pub fn describe(&self, x: f32, z: f32) -> String {
        let ll = self.lat_lon(x, z).map(|[lat, lon]| format_lat_lon(lat, lon));
        if self.georef.geographic {
            return ll.unwrap_or_default();
        }
        let [e, n] = self.world_to_crs(x, z);
        match ll {
            Some(ll) => format!("{ll} (E {e:.0}, N {n:.0})"),
            None => format!("E {e:.0}, N {n:.0}"),
        }
    }

    /// The CRS's name for the panel.
    pub fn crs(&self) -> &str {
        self.georef.crs.as_deref().unwrap_or("local")
    }

    /// World direction (x, z) of north: up the rows for a north-up raster.
    pub fn north(&self) -> [f32; 2] {
        if self.georef.step[1] < 0.0 {
            [0.0, -1.0]
        } else {
            [0.0, 1.0]
        }
    }
}

pub fn format_lat_lon(lat: f64, lon: f64) -> String {
    format!(
        "{:.5} {}, {:.5} {}",
        lat.abs(),
        if lat >= 0.0 { "N" } else { "S" },
        lon.abs(),
        if lon >= 0.0 { "E" } else { "W" }
    )
}

/// Parses "46.85, -121.76" or "46.85 N 121.76 W" (latitude first) into degrees.
pub fn parse_lat_lon(s: &str) -> Result<[f64; 2], String> {
    let bad = || format!("'{s}': expected latitude, longitude in degrees (46.85, -121.76 or 46.85 N 121.76 W)");
    let cleaned = s.replace([',', '°'], " ");
    let mut parts: Vec<String> = Vec::new();
    for tok in cleaned.split_whitespace() {
        let t = tok.to_uppercase();
        match t.as_str() {
            "N" | "S" | "E" | "W" => parts.last_mut().ok_or_else(bad)?.push_str(&t),
            _ => parts.push(t),
        }
    }
    if parts.len() != 2 {
        return Err(bad());
    }
    let value = |p: &str, pos: char, neg: char| -> Result<f64, String> {
        let (num, sign) = match p.chars().last() {
            Some(c) if c == pos => (&p[..p.len() - 1], 1.0),
            Some(c) if c == neg => (&p[..p.len() - 1], -1.0),
            Some(c) if c.is_ascii_alphabetic() => return Err(bad()),
            _ => (p, 1.0),
        };
        num.parse::<f64>().map(|v| v * sign).map_err(|_| bad())
    };
    let (lat, lon) = (value(&parts[0], 'N', 'S')?, value(&parts[1], 'E', 'W')?);
    if !(-90.0..=90.0).contains(&lat) {
        return Err(format!("'{s}': latitude {lat} is not within -90 to 90 degrees"));
    }
    if !(-180.0..=360.0).contains(&lon) {
        return Err(format!("'{s}': longitude {lon} is not within -180 to 360 degrees"));
    }
    Ok([lat, lon])
}

/// A scale bar for `metres_per_pixel`: the longest of 1, 2 or 5 times a power of ten
/// metres that fits in `max_pixels`, and its length in pixels.
pub fn scale_bar(metres_per_pixel: f32, max_pixels: f32) -> Option<(f32, f32)> {
    if !(metres_per_pixel.is_finite() && metres_per_pixel > 0.0) {
        return None;
    }
    let most = metres_per_pixel * max_pixels;
    let p = 10f32.powf(most.log10().floor());
    let m = [5.0, 2.0, 1.0].into_iter().map(|f| f * p).find(|&m| m <= most)?;
    Some((m, m / metres_per_pixel))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lat_lon_text() {
        assert_eq!(parse_lat_lon("46.85, -121.76").unwrap(), [46.85, -121.76]);
        assert_eq!(parse_lat_lon("46.85 N 121.76 W").unwrap(), [46.85, -121.76]);
        assert_eq!(parse_lat_lon("27.98S, 86.92E").unwrap(), [-27.98, 86.92]);
        assert!(parse_lat_lon("46.85").is_err());
        assert!(parse_lat_lon("95, 10").unwrap_err().contains("latitude 95 is not within"));
        assert!(parse_lat_lon("46.85,-181").unwrap_err().contains("longitude -181 is not within"));
        assert!(parse_lat_lon("nan, 10").is_err());
        assert!(parse_lat_lon("abc, 10").is_err());
        assert_eq!(format_lat_lon(-27.5, 86.25), "27.50000 S, 86.25000 E");
    }

    #[test]
    fn scale_bars_are_round() {
        assert_eq!(scale_bar(10.0, 120.0), Some((1000.0, 100.0)));
        assert_eq!(scale_bar(3.0, 120.0), Some((200.0, 200.0 / 3.0)));
        assert_eq!(scale_bar(0.0, 120.0), None);
    }

    /// A projected frame (UTM 10N, 25 m samples) round-trips world -> lat/lon -> world to
    /// a millimetre, and Mt Rainier's summit (46.8529 N, 121.7604 W) lands where UTM puts it.
    #[test]
    fn utm_round_trip() {
        let wkt = SpatialRef::from_epsg(32610).unwrap().to_wkt().unwrap();
        let g = Georef {
            crs: Some("EPSG:32610".into()),
            wkt,
            origin: [590_000.0, 5_195_000.0],
            step: [25.0, -25.0],
            ..Georef::default()
        };
        let geo = Geo::new(&g, Spacing::from(25.0)).unwrap();
        let (x, z) = geo.world_of(46.8529, -121.7604).unwrap();
        let [e, n] = geo.world_to_crs(x, z);
        // Rainier's summit in UTM 10N is about E 594,490, N 5,189,570 (to ~100 m: a
        // check against swapped axes or a wrong zone, which miss by kilometres).
        assert!((e - 594_490.0).abs() < 150.0 && (n - 5_189_570.0).abs() < 150.0, "{e} {n}");
        let [lat, lon] = geo.lat_lon(x, z).unwrap();
        assert!((lat - 46.8529).abs() < 1e-8 && (lon + 121.7604).abs() < 1e-8, "{lat} {lon}");
        assert_eq!(geo.north(), [0.0, -1.0]);
        // On a 10 km square from that origin the summit is on the terrain; a point just
        // beyond its east edge, the antipode and a latitude PROJ cannot map are refused,
        // each naming the corners the terrain spans.
        let extent = (10_000.0, 10_000.0);
        assert_eq!(geo.world_on_terrain(46.8529, -121.7604, extent).unwrap(), (x, z));
        let [lat, lon] = geo.lat_lon(10_050.0, 5_000.0).unwrap();
        for (lat, lon) in [(lat, lon), (-46.8529, 58.2396), (89.99, -121.76)] {
            let e = geo.world_on_terrain(lat, lon, extent).unwrap_err();
            assert!(e.contains("spans") && (e.contains("off the terrain") || e.contains("cannot be placed")), "{e}");
        }
    }
}
