#!/usr/bin/env python3
"""Measures a prepared archive against the alternatives named in issue 27 (docs/benchmarks.md
"Tile archive"): the PMTiles file as written, the same tiles in an MBTiles (SQLite) file, and
other tile compressions. Also checks the archive with the reference PMTiles reader (every
tile found where its payload says it is, every CRC-32 right).

  pip install pmtiles zstandard && python3 tools/archive_containers.py ARCHIVE.pmtiles
"""
import gzip, lzma, os, random, sqlite3, struct, sys, tempfile, time, zlib

import zstandard

from pmtiles.reader import MmapSource, Reader, all_tiles

path = sys.argv[1]
unzstd = zstandard.ZstdDecompressor().decompress
with open(path, "rb") as f:
    reader = Reader(MmapSource(f))
    assert reader.header()["tile_compression"].value == 4, "tiles are zstd"
    top = reader.header()["max_zoom"]
    tiles = []
    for (z, x, y), data in all_tiles(MmapSource(f)):
        p = unzstd(data)
        magic, _ver, _fmt, level, tx, tz, _side, crc = struct.unpack("<4sHBBIIII", p[:24])
        assert magic == b"VKTT" and (top - z, x, y) == (level, tx, tz), (z, x, y, level, tx, tz)
        assert zlib.crc32(p[24:]) == crc, (z, x, y)
        tiles.append(((z, x, y), data, p))
print(f"{path}: {len(tiles)} tiles, all read by the reference PMTiles reader, all CRC-32 right")
size = os.path.getsize(path)
payload = sum(len(d) for _, d, _ in tiles)
raw = sum(len(p) for _, _, p in tiles)
print(f"pmtiles file {size / 1e6:.2f} MB: tile data {payload / 1e6:.2f} MB, directories+metadata+header {(size - payload) / 1e3:.1f} kB")

random.seed(27)
sample = random.sample(tiles, min(400, len(tiles)))
with open(path, "rb") as f:
    reader = Reader(MmapSource(f))
    t0 = time.perf_counter()
    for (z, x, y), _, _ in sample:
        unzstd(reader.get(z, x, y))
    pm = (time.perf_counter() - t0) / len(sample)

with tempfile.TemporaryDirectory() as d:
    db = os.path.join(d, "t.mbtiles")
    con = sqlite3.connect(db)
    con.execute("create table tiles (zoom_level integer, tile_column integer, tile_row integer, tile_data blob)")
    con.execute("create unique index tile_index on tiles (zoom_level, tile_column, tile_row)")
    con.executemany("insert into tiles values (?, ?, ?, ?)", [(z, x, (1 << z) - 1 - y, data) for (z, x, y), data, _ in tiles])
    con.commit()
    con.close()
    mb_size = os.path.getsize(db)
    con = sqlite3.connect(db)
    t0 = time.perf_counter()
    for (z, x, y), _, _ in sample:
        (data,) = con.execute(
            "select tile_data from tiles where zoom_level=? and tile_column=? and tile_row=?", (z, x, (1 << z) - 1 - y)
        ).fetchone()
        unzstd(data)
    mb = (time.perf_counter() - t0) / len(sample)
print(f"mbtiles file {mb_size / 1e6:.2f} MB ({100 * mb_size / size:.1f} % of the pmtiles file)")
print(f"random tile read + decompress (the python PMTiles reader re-reads its directories on every call): pmtiles {pm * 1e3:.2f} ms, mbtiles {mb * 1e3:.2f} ms (page cache warm, {len(sample)} tiles)")

print(f"tile compression of {raw / 1e6:.1f} MB of payloads (row-differenced heights + D), on 60 of them:")
codecs = [("gzip 1", lambda b: gzip.compress(b, 1)), ("gzip 6", lambda b: gzip.compress(b, 6)),
          ("gzip 9", lambda b: gzip.compress(b, 9)), ("xz 6", lambda b: lzma.compress(b))]
codecs.append(("zstd 3 (written)", zstandard.ZstdCompressor(level=3).compress))
codecs.append(("zstd 19", zstandard.ZstdCompressor(level=19).compress))
subset = [p for _, _, p in sample[:60]]
sub_raw = sum(len(p) for p in subset)
decoders = {"gzip": gzip.decompress, "xz": lzma.decompress, "zstd": unzstd}
for name, fn in codecs:
    t0 = time.perf_counter()
    packed = [fn(p) for p in subset]
    dt = time.perf_counter() - t0
    t1 = time.perf_counter()
    for b in packed:
        decoders[name.split()[0]](b)
    du = time.perf_counter() - t1
    out = sum(len(b) for b in packed)
    print(f"  {name:18s} {100 * out / sub_raw:5.1f} % of raw, {sub_raw / dt / 1e6:6.1f} MB/s compressing, "
          f"{sub_raw / du / 1e6:7.1f} MB/s decompressing (python's C codecs, 1 core)")
