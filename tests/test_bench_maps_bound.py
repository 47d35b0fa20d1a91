"""tools/bench_maps.py: the localisation's coverage of the geometric bound (frames overlapping the map)."""

from tool_support import load_tool

bench_maps = load_tool("bench_maps")


def test_coverage_counts_only_overlapping_frames_and_tells_the_localiser_from_the_odometry(tmp_path):
    csv_path = tmp_path / "localization.csv"
    rows = [(300, "tracked"), (301, "relocalised"), (302, "odometry"), (303, "not_localised"), (304, "tracked")]
    csv_path.write_text("frame,timestamp,status,keyframe,inliers,position_std\n"
                        + "".join(f"{f},{f / 30},{s},,,\n" for f, s in rows), encoding="utf-8")
    # 304 is localised but does not overlap the map; 305 overlaps and is missing from the CSV (not posed)
    overlap = {300: 0.9, 301: 0.3, 302: 0.5, 303: 0.6, 304: 0.29, 305: 0.7}
    got = bench_maps.coverage_of_bound(csv_path, overlap)
    assert got == {"posed": 3, "posed_fraction": 3 / 5, "by_localiser": 2, "by_localiser_fraction": 2 / 5}
    assert bench_maps.coverage_of_bound(csv_path, {304: 0.1})["posed_fraction"] is None  # none overlaps
