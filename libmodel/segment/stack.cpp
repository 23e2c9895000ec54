// Slice stacks: listing in natural order, decoding with checks, sources.
#include "libmodel/format/atomic.h"
#include "libmodel/segment/segment.h"
#include "libmodel/provenance.h"

#include <jpeglib.h>
#include <png.h>
#include <tiffio.h>
#include <opencv2/core.hpp>
#include <opencv2/core/utils/logger.hpp>
#include <opencv2/imgcodecs.hpp>

#include <algorithm>
#include <array>
#include <bit>
#include <cctype>
#include <csetjmp>
#include <cstdarg>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <memory>
#include <mutex>
#include <sstream>

namespace orthosim {

namespace fs = std::filesystem;

bool natural_less(const std::string& a, const std::string& b) {
  std::size_t i = 0, j = 0;
  while (i < a.size() && j < b.size()) {
    const auto ca = static_cast<unsigned char>(a[i]), cb = static_cast<unsigned char>(b[j]);
    if (std::isdigit(ca) && std::isdigit(cb)) {
      // compare digit runs as numbers: skip leading zeros, then length, then digits
      std::size_t i0 = i, j0 = j;
      while (i < a.size() && std::isdigit(static_cast<unsigned char>(a[i]))) ++i;
      while (j < b.size() && std::isdigit(static_cast<unsigned char>(b[j]))) ++j;
      std::size_t ia = i0, jb = j0;
      while (ia + 1 < i && a[ia] == '0') ++ia;
      while (jb + 1 < j && b[jb] == '0') ++jb;
      const std::size_t la = i - ia, lb = j - jb;
      if (la != lb) return la < lb;
      const int c = a.compare(ia, la, b, jb, lb);
      if (c != 0) return c < 0;
      continue;
    }
    const int la = std::tolower(ca), lb = std::tolower(cb);
    if (la != lb) return la < lb;
    ++i, ++j;
  }
  if ((i < a.size()) != (j < b.size())) return j < b.size();
  return a < b;  // equal under the natural order: plain order decides
}

namespace {

bool is_image_name(const std::string& name) {
  auto dot = name.find_last_of('.');
  if (dot == std::string::npos) return false;
  std::string ext = name.substr(dot + 1);
  for (auto& c : ext) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  static const std::array<const char*, 7> known = {"png", "jpg", "jpeg", "jpe", "tif", "tiff", "bmp"};
  return std::find_if(known.begin(), known.end(), [&](const char* k) { return ext == k; }) != known.end();
}

std::vector<std::uint8_t> read_bytes(const std::string& path) {
  std::error_code ec;
  if (!fs::exists(path, ec)) throw Error(path, "slice file not found");
  if (!fs::is_regular_file(path, ec)) throw Error(path, "slice is not a regular file");
  std::ifstream in(path, std::ios::binary);
  if (!in) throw Error(path, "cannot open slice (unreadable)");
  in.seekg(0, std::ios::end);
  const auto size = static_cast<std::streamoff>(in.tellg());
  if (size <= 0) throw Error(path, "empty image file (0 bytes)");
  std::vector<std::uint8_t> bytes(static_cast<std::size_t>(size));
  in.seekg(0);
  if (!in.read(reinterpret_cast<char*>(bytes.data()), size)) throw Error(path, "cannot read slice (I/O error)");
  return bytes;
}

// CRC-32 (ISO-HDLC, as PNG uses), table driven.
std::uint32_t crc32(const std::uint8_t* p, std::size_t n, std::uint32_t crc = 0) {
  static const auto table = [] {
    std::array<std::array<std::uint32_t, 256>, 4> t{};
    for (std::uint32_t i = 0; i < 256; ++i) {
      std::uint32_t c = i;
      for (int k = 0; k < 8; ++k) c = c & 1 ? 0xEDB88320u ^ (c >> 1) : c >> 1;
      t[0][i] = c;
    }
    for (std::uint32_t i = 0; i < 256; ++i)
      for (int s = 1; s < 4; ++s) t[s][i] = (t[s - 1][i] >> 8) ^ t[0][t[s - 1][i] & 0xFF];
    return t;
  }();
  crc = ~crc;
  while (n >= 4) {  // slicing by 4
    crc ^= static_cast<std::uint32_t>(p[0]) | static_cast<std::uint32_t>(p[1]) << 8 |
           static_cast<std::uint32_t>(p[2]) << 16 | static_cast<std::uint32_t>(p[3]) << 24;
    crc = table[3][crc & 0xFF] ^ table[2][(crc >> 8) & 0xFF] ^ table[1][(crc >> 16) & 0xFF] ^ table[0][crc >> 24];
    p += 4, n -= 4;
  }
  while (n--) crc = table[0][(crc ^ *p++) & 0xFF] ^ (crc >> 8);
  return ~crc;
}

std::uint32_t be32(const std::uint8_t* p) {
  return static_cast<std::uint32_t>(p[0]) << 24 | static_cast<std::uint32_t>(p[1]) << 16 |
         static_cast<std::uint32_t>(p[2]) << 8 | p[3];
}

// libjpeg's errors and warnings, each a failure: under OpenCV a warning
// ("Corrupt JPEG data: premature end of data segment") went to stderr and the
// slice came back with decoder fill, segmented as tissue (sweep of 2026-11-27).
struct JpegErrors {
  jpeg_error_mgr mgr;  // first: libjpeg sees a jpeg_error_mgr*
  std::jmp_buf jump;
  char message[JMSG_LENGTH_MAX];
};
[[noreturn]] void jpeg_fail(j_common_ptr c) {
  auto* e = reinterpret_cast<JpegErrors*>(c->err);
  (*c->err->format_message)(c, e->message);
  std::longjmp(e->jump, 1);
}
void jpeg_message(j_common_ptr c, int level) {
  if (level < 0) jpeg_fail(c);  // -1: a warning (corrupt data); >= 0: trace messages, ignored
}

// Decodes the whole entropy-coded stream (at 1/8 scale: every Huffman code is
// read, the inverse transforms are the DC terms only) and throws on the first
// error or warning. Only C objects live between setjmp and longjmp.
void check_jpeg_data(const std::string& path, const std::vector<std::uint8_t>& b) {
  jpeg_decompress_struct cinfo{};
  JpegErrors err{};
  cinfo.err = jpeg_std_error(&err.mgr);
  err.mgr.error_exit = jpeg_fail;
  err.mgr.emit_message = jpeg_message;
  if (setjmp(err.jump)) {
    jpeg_destroy_decompress(&cinfo);
    std::string what = err.message;  // libjpeg's own warnings start "Corrupt JPEG data: "
    if (what.rfind("Corrupt JPEG data: ", 0) == 0) what.erase(0, 19);
    throw Error(path, "corrupt JPEG: " + what);
  }
  jpeg_create_decompress(&cinfo);
  jpeg_mem_src(&cinfo, b.data(), static_cast<unsigned long>(b.size()));
  jpeg_read_header(&cinfo, TRUE);
  cinfo.scale_num = 1;
  cinfo.scale_denom = 8;
  cinfo.dct_method = JDCT_IFAST;
  cinfo.do_fancy_upsampling = FALSE;
  jpeg_start_decompress(&cinfo);
  JSAMPARRAY row = (*cinfo.mem->alloc_sarray)(reinterpret_cast<j_common_ptr>(&cinfo), JPOOL_IMAGE,
                                              cinfo.output_width * static_cast<JDIMENSION>(cinfo.output_components), 1);
  while (cinfo.output_scanline < cinfo.output_height) jpeg_read_scanlines(&cinfo, row, 1);
  jpeg_finish_decompress(&cinfo);
  jpeg_destroy_decompress(&cinfo);
}

// Structural checks before decoding, so that a corrupt file gives one clear
// error instead of a decoder's messages on stderr or a half-grey image.
void check_container(const std::string& path, const std::vector<std::uint8_t>& b) {
  static const std::uint8_t png_sig[8] = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n'};
  if (b.size() >= 8 && std::equal(png_sig, png_sig + 8, b.begin())) {
    std::size_t at = 8;
    bool first = true, end = false;
    while (!end) {
      if (at + 12 > b.size()) throw Error(path, "corrupt PNG: truncated (no IEND chunk)");
      const std::uint32_t len = be32(&b[at]);
      if (len > b.size() - at - 12) throw Error(path, "corrupt PNG: truncated chunk");
      const std::uint8_t* type = &b[at + 4];
      if (first && std::string(reinterpret_cast<const char*>(type), 4) != "IHDR")
        throw Error(path, "corrupt PNG: first chunk is not IHDR");
      if (crc32(type, len + 4) != be32(&b[at + 8 + len]))
        throw Error(path, "corrupt PNG: CRC mismatch in chunk '" + std::string(reinterpret_cast<const char*>(type), 4) +
                              "'");
      end = std::string(reinterpret_cast<const char*>(type), 4) == "IEND";
      first = false;
      at += 12 + len;
    }
    return;
  }
  if (b.size() >= 2 && b[0] == 0xFF && b[1] == 0xD8) {
    // the end-of-image marker must be there (allow trailing padding)
    const std::size_t from = b.size() > 4096 ? b.size() - 4096 : 2;
    bool eoi = false;
    for (std::size_t i = b.size() - 1; i > from && !eoi; --i) eoi = b[i - 1] == 0xFF && b[i] == 0xD9;
    if (!eoi) throw Error(path, "corrupt JPEG: truncated (no end-of-image marker)");
  }
}

bool is_jpeg(const std::vector<std::uint8_t>& b) { return b.size() >= 2 && b[0] == 0xFF && b[1] == 0xD8; }
bool is_png(const std::vector<std::uint8_t>& b) {
  static const std::uint8_t sig[8] = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n'};
  return b.size() >= 8 && std::equal(sig, sig + 8, b.begin());
}

// A region x, y, w, h of a slice nx x ny (w = 0: the whole slice).
bool whole(const std::array<int, 4>& r) { return r[2] == 0 && r[3] == 0; }
std::array<int, 4> region_in(const std::array<int, 4>& r, int nx, int ny) {
  return whole(r) ? std::array<int, 4>{0, 0, nx, ny} : r;
}
bool region_fits(const std::array<int, 4>& r, int nx, int ny) {
  return r[0] >= 0 && r[1] >= 0 && r[2] > 0 && r[3] > 0 && static_cast<std::int64_t>(r[0]) + r[2] <= nx &&
         static_cast<std::int64_t>(r[1]) + r[3] <= ny;
}
[[noreturn]] void region_beyond(const std::string& path, const std::array<int, 4>& r, int nx, int ny) {
  throw Error(path, "the region (x " + std::to_string(r[0]) + ", y " + std::to_string(r[1]) + ", " + std::to_string(r[2]) +
                        " x " + std::to_string(r[3]) + " px) reaches beyond the slice, which is " + std::to_string(nx) +
                        " x " + std::to_string(ny) + " px");
}

// ---- the decoders ------------------------------------------------------------------------------
// JPEG, PNG and TIFF slices are decoded here, straight into the RGB image, of
// the region alone (read_slice's region); other files by OpenCV, whole, then
// cut. Each gives the values cv::imdecode(IMREAD_UNCHANGED) gives (SliceRegion
// tests), or returns false before decoding anything for a file it leaves to
// OpenCV. Between each setjmp and its longjmp (libjpeg's and libpng's errors)
// only C objects live; the caller owns the C++ ones (the image, the row buffer).

// n pixels of a decoded row (3 or 4 channels, 8 or 16 bits in host order, in
// RGB order or BGR when bgr) as 8-bit RGB: 16-bit values scaled from
// bit_depth significant bits (v x 255 / (2^bit_depth - 1), rounded, clamped),
// the largest 16-bit colour value kept in *max_value, alpha dropped.
void to_rgb8(const std::uint8_t* src, int n, int channels, int bits, bool bgr, int bit_depth, std::uint8_t* dst,
             int* max_value) {
  const int r = bgr ? 2 : 0, b = bgr ? 0 : 2;
  if (bits == 8) {
    if (channels == 3 && !bgr) {
      std::memcpy(dst, src, static_cast<std::size_t>(n) * 3);
      return;
    }
    for (int x = 0; x < n; ++x) {
      dst[3 * x + 0] = src[channels * x + r];
      dst[3 * x + 1] = src[channels * x + 1];
      dst[3 * x + 2] = src[channels * x + b];
    }
    return;
  }
  const std::uint32_t full = (1u << bit_depth) - 1;  // the largest value of the significant bits
  int most = *max_value;
  for (int x = 0; x < n; ++x)
    for (int c = 0; c < 3; ++c) {
      std::uint16_t v = 0;  // (copied: the bytes are not uint16_t objects)
      std::memcpy(&v, src + 2 * static_cast<std::size_t>(channels * x + (c == 0 ? r : c == 2 ? b : 1)), 2);
      most = std::max(most, static_cast<int>(v));
      dst[3 * x + c] = static_cast<std::uint8_t>(std::min<std::uint32_t>(255, (v * 255 + full / 2) / full));
    }
  *max_value = most;
}

// JPEG, 3 components in YCbCr or RGB: the region's rows and (jpeg_crop_scanline)
// its iMCU columns, with a margin of two iMCUs on each side. Without a margin
// the columns next to a crop's border differed from the whole slice's
// (SliceRegion.ARegionIsTheWholeSliceCutInEveryFormat: 4:2:0 and 4:4:4 files
// alike); with one iMCU they did not; the rows above a region, skipped, needed
// none on those files, and get the same margin. The rows above are skipped
// (jpeg_skip_scanlines: their entropy codes read, no inverse transform), and
// the rows below skipped to the last, which is read, so that the whole stream
// is checked as check_jpeg_data checks it (skipping to the very end stops
// reading it: libjpeg-turbo marks the end reached). libjpeg's warnings are
// errors (JpegErrors). (OpenCV asks for JCS_RGB too, then swaps to BGR.)
struct JpegRegion {
  jpeg_decompress_struct cinfo;
  JpegErrors err;
  const std::uint8_t* bytes;
  unsigned long size;
  int nx, ny, components;
  J_COLOR_SPACE space;
};

// 0: read; 1: an error (err.message)
int jpeg_header(JpegRegion& j) {
  j.cinfo.err = jpeg_std_error(&j.err.mgr);
  j.err.mgr.error_exit = jpeg_fail;
  j.err.mgr.emit_message = jpeg_message;
  if (setjmp(j.err.jump)) return 1;
  jpeg_create_decompress(&j.cinfo);
  jpeg_mem_src(&j.cinfo, j.bytes, j.size);
  jpeg_read_header(&j.cinfo, TRUE);
  j.nx = static_cast<int>(j.cinfo.image_width), j.ny = static_cast<int>(j.cinfo.image_height);
  j.components = j.cinfo.num_components;
  j.space = j.cinfo.jpeg_color_space;
  return 0;
}

// the region r's RGB pixels to out (r[2] * 3 bytes a row)
int jpeg_rows(JpegRegion& j, const int* r, std::uint8_t* out) {
  if (setjmp(j.err.jump)) return 1;
  jpeg_decompress_struct& c = j.cinfo;
  c.out_color_space = JCS_RGB;
  jpeg_start_decompress(&c);
  const int imcu = std::max(c.max_h_samp_factor, c.max_v_samp_factor) * DCTSIZE;
  const int margin = 2 * imcu;
  JDIMENSION x0 = static_cast<JDIMENSION>(std::max(0, r[0] - margin));
  JDIMENSION width = static_cast<JDIMENSION>(std::min(j.nx, r[0] + r[2] + margin)) - x0;
  if (width < c.output_width) jpeg_crop_scanline(&c, &x0, &width);  // x0 down to an iMCU's edge
  JSAMPARRAY row = (*c.mem->alloc_sarray)(reinterpret_cast<j_common_ptr>(&c), JPOOL_IMAGE, c.output_width * 3, 1);
  const JDIMENSION top = static_cast<JDIMENSION>(std::max(0, r[1] - margin));
  if (top > 0) jpeg_skip_scanlines(&c, top);
  const JDIMENSION first = static_cast<JDIMENSION>(r[1]), end = static_cast<JDIMENSION>(r[1] + r[3]);
  const std::size_t from = (static_cast<std::size_t>(r[0]) - x0) * 3, bytes = static_cast<std::size_t>(r[2]) * 3;
  const bool direct = from == 0 && c.output_width == static_cast<JDIMENSION>(r[2]);  // whole rows: straight into out
  while (c.output_scanline < end) {
    const JDIMENSION y = c.output_scanline;
    std::uint8_t* dst = y >= first ? out + (y - first) * bytes : nullptr;
    JSAMPROW into = direct && dst ? dst : row[0];
    jpeg_read_scanlines(&c, &into, 1);
    if (!direct && dst) std::memcpy(dst, row[0] + from, bytes);
  }
  // the rest of the stream, checked: its last row is read
  if (c.output_height - c.output_scanline > 1) jpeg_skip_scanlines(&c, c.output_height - c.output_scanline - 1);
  while (c.output_scanline < c.output_height) jpeg_read_scanlines(&c, row, 1);
  jpeg_finish_decompress(&c);
  return 0;
}

// Fills f; img gets the region's pixels, or stays empty when the region does
// not fit (read_slice says so).
bool decode_jpeg(const std::string& path, const std::vector<std::uint8_t>& b, const std::array<int, 4>& region,
                 RgbImage& img, SliceFormat& f) {
  JpegRegion j{};
  j.bytes = b.data();
  j.size = static_cast<unsigned long>(b.size());
  struct Destroy {
    JpegRegion& j;
    ~Destroy() { jpeg_destroy_decompress(&j.cinfo); }
  } destroy{j};
  auto fail = [&] {
    std::string what = j.err.message;  // libjpeg's own warnings start "Corrupt JPEG data: "
    if (what.rfind("Corrupt JPEG data: ", 0) == 0) what.erase(0, 19);
    throw Error(path, "corrupt JPEG: " + what);
  };
  if (jpeg_header(j) != 0) fail();
  if (j.components != 3 || (j.space != JCS_YCbCr && j.space != JCS_RGB)) return false;
  f.nx = j.nx, f.ny = j.ny, f.channels = 3, f.bits = 8;
  const std::array<int, 4> r = region_in(region, j.nx, j.ny);
  if (!region_fits(r, j.nx, j.ny) || static_cast<std::int64_t>(j.nx) * j.ny > (std::int64_t(1) << 28)) return true;
  img.nx = r[2], img.ny = r[3];
  img.rgb.resize(static_cast<std::size_t>(r[2]) * r[3] * 3);
  if (jpeg_rows(j, r.data(), img.rgb.data()) != 0) fail();
  return true;
}

// PNG, 8- or 16-bit RGB or RGBA, not interlaced, no tRNS chunk: the rows
// down to the region's last (a PNG row is filtered against the one above, so
// the rows above are decoded too; its columns cannot be cut before). The
// rows below are not inflated: check_container has checked every chunk's CRC.
struct PngRegion {
  png_structp png;
  png_infop info;
  const std::uint8_t* bytes;
  std::size_t size, at;
  char message[256];
  png_uint_32 nx, ny;
  int depth, type, interlace, trns;
};
void png_fail(png_structp p, png_const_charp msg) {
  auto* j = static_cast<PngRegion*>(png_get_error_ptr(p));
  std::snprintf(j->message, sizeof j->message, "%s", msg);
  png_longjmp(p, 1);
}
void png_warning_ignored(png_structp, png_const_charp) {}  // (OpenCV's decoder shows none either)
void png_read_bytes(png_structp p, png_bytep out, png_size_t n) {
  auto* j = static_cast<PngRegion*>(png_get_io_ptr(p));
  if (n > j->size - j->at) png_error(p, "truncated");
  std::memcpy(out, j->bytes + j->at, n);
  j->at += n;
}

int png_header(PngRegion& j) {
  j.png = png_create_read_struct(PNG_LIBPNG_VER_STRING, &j, png_fail, png_warning_ignored);
  if (!j.png) return 1;
  j.info = png_create_info_struct(j.png);
  if (!j.info) return 1;
  if (setjmp(png_jmpbuf(j.png))) return 1;
  png_set_read_fn(j.png, &j, png_read_bytes);
  png_read_info(j.png, j.info);
  png_get_IHDR(j.png, j.info, &j.nx, &j.ny, &j.depth, &j.type, &j.interlace, nullptr, nullptr);
  j.trns = png_get_valid(j.png, j.info, PNG_INFO_tRNS) != 0;
  return 0;
}

// rows 0 .. r[1] + r[3] - 1 through `line` (one row of the file); the
// region's part of each to out as 8-bit RGB (to_rgb8)
int png_rows(PngRegion& j, const int* r, int channels, int bit_depth, std::uint8_t* line, std::uint8_t* out,
             int* max_value) {
  if (setjmp(png_jmpbuf(j.png))) return 1;
  // the check of each chunk's CRC, made again as it is read, is
  // check_container's (as OpenCV's decoder, libpng would check it here too)
  if (j.depth == 16) png_set_swap(j.png);  // (this build is little-endian: host order, as OpenCV's)
  png_read_update_info(j.png, j.info);
  const int pixel = channels * j.depth / 8;
  const std::size_t from = static_cast<std::size_t>(r[0]) * pixel, bytes = static_cast<std::size_t>(r[2]) * 3;
  // 8-bit RGB, whole rows: straight into out
  const bool direct = j.depth == 8 && channels == 3 && r[0] == 0 && r[2] == static_cast<int>(j.nx);
  for (int y = 0; y < r[1] + r[3]; ++y) {
    std::uint8_t* dst = y >= r[1] ? out + static_cast<std::size_t>(y - r[1]) * bytes : nullptr;
    png_read_row(j.png, direct && dst ? dst : line, nullptr);
    if (!direct && dst) to_rgb8(line + from, r[2], channels, j.depth, false, bit_depth, dst, max_value);
  }
  return 0;
}

bool decode_png(const std::string& path, const std::vector<std::uint8_t>& b, const std::array<int, 4>& region,
                int bit_depth, RgbImage& img, SliceFormat& f) {
  static_assert(std::endian::native == std::endian::little, "png_rows swaps 16-bit samples to little-endian");
  PngRegion j{};
  j.bytes = b.data();
  j.size = b.size();
  struct Destroy {
    PngRegion& j;
    ~Destroy() {
      if (j.png) png_destroy_read_struct(&j.png, j.info ? &j.info : nullptr, nullptr);
    }
  } destroy{j};
  auto fail = [&] { throw Error(path, std::string("corrupt PNG: ") + (j.message[0] ? j.message : "cannot read it")); };
  if (png_header(j) != 0) fail();
  if ((j.type != PNG_COLOR_TYPE_RGB && j.type != PNG_COLOR_TYPE_RGB_ALPHA) || (j.depth != 8 && j.depth != 16) ||
      j.interlace != PNG_INTERLACE_NONE || j.trns || j.nx > (1u << 28) || j.ny > (1u << 28))
    return false;
  const int nx = static_cast<int>(j.nx), ny = static_cast<int>(j.ny);
  const int channels = j.type == PNG_COLOR_TYPE_RGB ? 3 : 4;
  f.nx = nx, f.ny = ny, f.channels = channels, f.bits = j.depth;
  const std::array<int, 4> r = region_in(region, nx, ny);
  if (!region_fits(r, nx, ny) || static_cast<std::int64_t>(nx) * ny > (std::int64_t(1) << 28)) return true;
  img.nx = r[2], img.ny = r[3];
  img.rgb.resize(static_cast<std::size_t>(r[2]) * r[3] * 3);
  std::vector<std::uint8_t> line(static_cast<std::size_t>(nx) * channels * j.depth / 8);
  if (png_rows(j, r.data(), channels, bit_depth, line.data(), img.rgb.data(), &f.max_value) != 0) fail();
  return true;
}

// TIFF, RGB, 8 bits with 3 samples or 16 bits with 3 or 4, in strips,
// contiguous, top-left orientation: the strips the region's rows lie in,
// each decoded by libtiff (its compression, predictor and byte order) as
// OpenCV's decoder reads them (TIFFReadEncodedStrip; for 8 bits OpenCV reads
// through TIFFReadRGBAStrip, whose values for these files are the samples
// themselves: SliceRegion tests). Strips are independent, so the rows above
// and below a region are neither read nor checked. libtiff's errors are the
// error (its warnings, as for OpenCV, are not shown).
struct TiffMemory {
  const std::uint8_t* bytes;
  std::size_t size, at;
  char message[256];
};
tmsize_t tiff_read(thandle_t h, void* out, tmsize_t n) {
  auto* m = static_cast<TiffMemory*>(h);
  if (n <= 0 || m->at >= m->size) return 0;  // (a seek may have gone past the end)
  const std::size_t k = std::min(static_cast<std::size_t>(n), m->size - m->at);
  std::memcpy(out, m->bytes + m->at, k);
  m->at += k;
  return static_cast<tmsize_t>(k);
}
tmsize_t tiff_write(thandle_t, void*, tmsize_t) { return 0; }
toff_t tiff_seek(thandle_t h, toff_t off, int whence) {
  auto* m = static_cast<TiffMemory*>(h);
  const std::uint64_t base = whence == SEEK_SET ? 0 : whence == SEEK_CUR ? m->at : m->size;
  m->at = static_cast<std::size_t>(base + off);
  return static_cast<toff_t>(m->at);
}
int tiff_close(thandle_t) { return 0; }
toff_t tiff_size(thandle_t h) { return static_cast<toff_t>(static_cast<TiffMemory*>(h)->size); }
int tiff_map(thandle_t h, void** base, toff_t* size) {
  auto* m = static_cast<TiffMemory*>(h);
  *base = const_cast<std::uint8_t*>(m->bytes);
  *size = static_cast<toff_t>(m->size);
  return 1;
}
void tiff_unmap(thandle_t, void*, toff_t) {}
int tiff_error(TIFF*, void* user, const char* module, const char* fmt, va_list ap) {
  auto* m = static_cast<TiffMemory*>(user);
  if (m->message[0] == 0) {  // the first: the cause
    char text[200];
    std::vsnprintf(text, sizeof text, fmt, ap);
    std::snprintf(m->message, sizeof m->message, "%s%s%s", module ? module : "", module ? ": " : "", text);
  }
  return 1;  // handled: not printed
}
int tiff_warning(TIFF*, void*, const char*, const char*, va_list) { return 1; }

bool is_tiff(const std::vector<std::uint8_t>& b) {
  return b.size() >= 4 && ((b[0] == 'I' && b[1] == 'I' && b[2] == 42 && b[3] == 0) ||
                           (b[0] == 'M' && b[1] == 'M' && b[2] == 0 && b[3] == 42));
}

bool decode_tiff(const std::string& path, const std::vector<std::uint8_t>& b, const std::array<int, 4>& region,
                 int bit_depth, RgbImage& img, SliceFormat& f) {
  TiffMemory mem{b.data(), b.size(), 0, {}};
  std::unique_ptr<TIFFOpenOptions, void (*)(TIFFOpenOptions*)> opts(TIFFOpenOptionsAlloc(), TIFFOpenOptionsFree);
  TIFFOpenOptionsSetErrorHandlerExtR(opts.get(), tiff_error, &mem);
  TIFFOpenOptionsSetWarningHandlerExtR(opts.get(), tiff_warning, &mem);
  std::unique_ptr<TIFF, void (*)(TIFF*)> t(TIFFClientOpenExt("slice", "r", &mem, tiff_read, tiff_write, tiff_seek,
                                                             tiff_close, tiff_size, tiff_map, tiff_unmap, opts.get()),
                                           TIFFClose);
  auto fail = [&] { throw Error(path, std::string("corrupt TIFF: ") + (mem.message[0] ? mem.message : "cannot read it")); };
  if (!t) fail();
  std::uint32_t nx = 0, ny = 0, rows_per_strip = 0;
  std::uint16_t spp = 0, bps = 0, photometric = 0, planar = 0, format = 0, orientation = 0;
  if (!TIFFGetField(t.get(), TIFFTAG_IMAGEWIDTH, &nx) || !TIFFGetField(t.get(), TIFFTAG_IMAGELENGTH, &ny) ||
      !TIFFGetField(t.get(), TIFFTAG_PHOTOMETRIC, &photometric))
    return false;
  TIFFGetFieldDefaulted(t.get(), TIFFTAG_SAMPLESPERPIXEL, &spp);
  TIFFGetFieldDefaulted(t.get(), TIFFTAG_BITSPERSAMPLE, &bps);
  TIFFGetFieldDefaulted(t.get(), TIFFTAG_PLANARCONFIG, &planar);
  TIFFGetFieldDefaulted(t.get(), TIFFTAG_SAMPLEFORMAT, &format);
  TIFFGetFieldDefaulted(t.get(), TIFFTAG_ORIENTATION, &orientation);
  TIFFGetFieldDefaulted(t.get(), TIFFTAG_ROWSPERSTRIP, &rows_per_strip);
  const bool layout = photometric == PHOTOMETRIC_RGB && planar == PLANARCONFIG_CONTIG && format == SAMPLEFORMAT_UINT &&
                      orientation == ORIENTATION_TOPLEFT && !TIFFIsTiled(t.get()) && rows_per_strip > 0 &&
                      ((bps == 8 && spp == 3) || (bps == 16 && (spp == 3 || spp == 4)));
  if (!layout || nx == 0 || ny == 0 || nx > (1u << 28) || ny > (1u << 28)) return false;
  f.nx = static_cast<int>(nx), f.ny = static_cast<int>(ny), f.channels = spp, f.bits = bps;
  const std::array<int, 4> r = region_in(region, f.nx, f.ny);
  if (!region_fits(r, f.nx, f.ny) || static_cast<std::int64_t>(nx) * ny > (std::int64_t(1) << 28)) return true;
  const std::size_t row_bytes = static_cast<std::size_t>(nx) * spp * bps / 8;
  const tmsize_t strip_bytes = TIFFStripSize(t.get());
  if (strip_bytes <= 0 || static_cast<std::size_t>(strip_bytes) < row_bytes) fail();
  std::vector<std::uint8_t> strip(static_cast<std::size_t>(strip_bytes));
  img.nx = r[2], img.ny = r[3];
  img.rgb.resize(static_cast<std::size_t>(r[2]) * r[3] * 3);
  const std::size_t from = static_cast<std::size_t>(r[0]) * spp * bps / 8;
  for (std::uint32_t s = static_cast<std::uint32_t>(r[1]) / rows_per_strip; s * rows_per_strip < static_cast<std::uint32_t>(r[1] + r[3]); ++s) {
    const std::uint32_t y0 = s * rows_per_strip, rows = std::min(rows_per_strip, ny - y0);
    if (TIFFReadEncodedStrip(t.get(), s, strip.data(), static_cast<tmsize_t>(rows * row_bytes)) < static_cast<tmsize_t>(rows * row_bytes))
      fail();
    for (std::uint32_t y = std::max(y0, static_cast<std::uint32_t>(r[1])); y < std::min(y0 + rows, static_cast<std::uint32_t>(r[1] + r[3])); ++y)
      to_rgb8(strip.data() + (y - y0) * row_bytes + from, r[2], spp, bps, false, bit_depth,
              img.rgb.data() + static_cast<std::size_t>(y - static_cast<std::uint32_t>(r[1])) * r[2] * 3, &f.max_value);
  }
  return true;
}

}  // namespace

std::vector<std::string> list_stack(const std::string& dir) {
  std::error_code ec;
  if (!fs::exists(dir, ec)) throw Error(dir, "stack folder not found");
  if (!fs::is_directory(dir, ec)) throw Error(dir, "stack is not a folder");
  std::vector<std::string> names;
  for (const auto& e : fs::directory_iterator(dir, ec)) {
    const std::string name = e.path().filename().string();
    if (name.empty() || name[0] == '.') continue;
    if (!is_image_name(name)) continue;
    names.push_back(name);
  }
  if (ec) throw Error(dir, "cannot list stack folder: " + ec.message());
  if (names.empty()) throw Error(dir, "no image slices (png, jpg, tif, bmp) in the stack folder");
  std::sort(names.begin(), names.end(), natural_less);
  std::vector<std::string> out;
  for (const auto& n : names) out.push_back((fs::path(dir) / n).string());
  return out;
}

std::string hash_stack(const std::string& dir, int first_slice, int last_slice) {
  std::string parts;
  const std::vector<std::string> files = list_stack(dir);
  for (std::size_t i = 0; i < files.size(); ++i) {
    const int z = static_cast<int>(i);
    const bool read = z == 0 || (z >= first_slice && (last_slice < 0 || z <= last_slice));
    parts += fs::path(files[i]).filename().string();
    parts += '\0';
    if (read) parts += hash_path(files[i]);
    parts += '\0';
  }
  return "xxh3:" + hash_bytes(parts.data(), parts.size());
}

namespace {

// OpenCV's decoders write some failures straight to std::cerr (imdecode's
// "imdecode_(''): can't read data: ... TIFFReadRGBAStrip ..." on a truncated
// TIFF) before orthosim's one-line error. While any slice decodes, std::cerr
// goes to a sink; slices decode in parallel, so the first decoder in
// redirects and the last one out restores (orthosim itself writes nothing to
// std::cerr meanwhile: errors are reported after the read).
class QuietCerr {
 public:
  QuietCerr() {
    std::lock_guard<std::mutex> lock(mutex());
    if (depth()++ == 0) saved() = std::cerr.rdbuf(sink().rdbuf());
  }
  ~QuietCerr() {
    std::lock_guard<std::mutex> lock(mutex());
    if (--depth() == 0) {
      std::cerr.rdbuf(saved());
      sink().str("");
    }
  }
  QuietCerr(const QuietCerr&) = delete;
  QuietCerr& operator=(const QuietCerr&) = delete;

 private:
  static std::mutex& mutex() {
    static std::mutex m;
    return m;
  }
  static int& depth() {
    static int d = 0;
    return d;
  }
  static std::streambuf*& saved() {
    static std::streambuf* b = nullptr;
    return b;
  }
  static std::ostringstream& sink() {
    static std::ostringstream s;
    return s;
  }
};

}  // namespace

RgbImage read_slice(const std::string& path, SliceFormat* format, int bit_depth, const std::array<int, 4>& region) {
  if (bit_depth < 8 || bit_depth > 16) throw Error(path, "bit depth must be in 8..16, not " + std::to_string(bit_depth));
  // OpenCV's own log lines ("[ WARN:0@0.037] global .../grfmt_tiff.cpp ...") stood
  // beside orthosim's one-line error on a corrupt TIFF or BMP
  static const bool silenced = [] {
    cv::utils::logging::setLogLevel(cv::utils::logging::LOG_LEVEL_SILENT);
    return true;
  }();
  (void)silenced;
  const std::vector<std::uint8_t> bytes = read_bytes(path);
  check_container(path, bytes);
  RgbImage img;
  SliceFormat f;
  const bool decoded = is_jpeg(bytes)  ? decode_jpeg(path, bytes, region, img, f)
                       : is_png(bytes)  ? decode_png(path, bytes, region, bit_depth, img, f)
                       : is_tiff(bytes) ? decode_tiff(path, bytes, region, bit_depth, img, f)
                                        : false;
  cv::Mat m;  // OpenCV's decoding, BGR(A)
  if (!decoded) {
    if (is_jpeg(bytes)) check_jpeg_data(path, bytes);
    try {
      const QuietCerr quiet;
      m = cv::imdecode(cv::Mat(1, static_cast<int>(bytes.size()), CV_8U, const_cast<std::uint8_t*>(bytes.data())),
                       cv::IMREAD_UNCHANGED);
    } catch (const cv::Exception& e) {
      throw Error(path, "cannot decode image (corrupt or unsupported)");
    }
    if (m.empty() || m.dims != 2 || m.rows <= 0 || m.cols <= 0)
      throw Error(path, "cannot decode image (corrupt, truncated or unsupported format)");
    f.nx = m.cols;
    f.ny = m.rows;
    f.channels = m.channels();
    if (m.depth() == CV_8U) {
      f.bits = 8;
    } else if (m.depth() == CV_16U) {
      f.bits = 16;
    } else {
      throw Error(path, "unsupported pixel type (only 8- and 16-bit unsigned images)");
    }
  }
  if (format) *format = f;
  if (f.channels < 3)
    throw Error(path, "grey-scale image (" + std::to_string(f.channels) +
                          " channel" + (f.channels == 1 ? "" : "s") + "): segmentation needs colour slices");
  if (static_cast<std::int64_t>(f.nx) * f.ny > (std::int64_t(1) << 28))
    throw Error(path, "slice too large (more than 2^28 pixels)");
  const std::array<int, 4> r = region_in(region, f.nx, f.ny);
  if (!region_fits(r, f.nx, f.ny)) region_beyond(path, r, f.nx, f.ny);
  if (!decoded) {
    img.nx = r[2];
    img.ny = r[3];
    img.rgb.resize(static_cast<std::size_t>(img.nx) * img.ny * 3);
    for (int y = 0; y < img.ny; ++y)
      to_rgb8(m.ptr<std::uint8_t>(y + r[1]) + static_cast<std::size_t>(r[0]) * m.elemSize(), img.nx, f.channels,
              f.bits, true, bit_depth, img.rgb.data() + static_cast<std::size_t>(y) * img.nx * 3, &f.max_value);
    if (format) format->max_value = f.max_value;
  }
  std::int64_t grey = 0, total = 0;
  for (int y = 0; y < img.ny; y += 4) {
    const std::uint8_t* row = img.rgb.data() + static_cast<std::size_t>(y) * img.nx * 3;
    for (int x = 0; x < img.nx; x += 4) {
      ++total;
      grey += row[3 * x] == row[3 * x + 1] && row[3 * x + 1] == row[3 * x + 2];
    }
  }
  if (total > 0 && grey * 1000 >= total * 999)
    throw Error(path, "grey-scale image stored as colour (R = G = B everywhere): segmentation needs colour slices");
  return img;
}

void write_png(const std::string& path, const RgbImage& image) {
  if (image.nx <= 0 || image.ny <= 0 || image.rgb.size() != static_cast<std::size_t>(image.nx) * image.ny * 3)
    throw Error(path, "image size does not match its pixels");
  cv::Mat bgr(image.ny, image.nx, CV_8UC3);
  for (int y = 0; y < image.ny; ++y) {
    auto* row = bgr.ptr<std::uint8_t>(y);
    const std::uint8_t* src = image.rgb.data() + static_cast<std::size_t>(y) * image.nx * 3;
    for (int x = 0; x < image.nx; ++x) {
      row[3 * x + 0] = src[3 * x + 2];
      row[3 * x + 1] = src[3 * x + 1];
      row[3 * x + 2] = src[3 * x + 0];
    }
  }
  std::vector<std::uint8_t> buf;
  if (!cv::imencode(".png", bgr, buf)) throw Error(path, "cannot encode PNG");
  AtomicFile out(path);
  {
    std::ofstream f(out.temp(), std::ios::binary);
    if (!f || !f.write(reinterpret_cast<const char*>(buf.data()), static_cast<std::streamsize>(buf.size())))
      throw Error(path, "cannot write image");
  }
  out.commit();
}

SliceSource stack_source(const std::string& dir, int bit_depth) {
  auto files = std::make_shared<std::vector<std::string>>(list_stack(dir));
  SliceFormat first;
  read_slice(files->front(), &first, bit_depth);  // size, channels and colour of the stack
  SliceSource s;
  s.nx = first.nx;
  s.ny = first.ny;
  s.nz = static_cast<int>(files->size());
  s.name = dir;
  if (first.bits == 16) {
    // a 12-bit camera's data read as 16-bit is 16x too dark: 'nothing
    // segmented', with no hint why
    int used = 1;
    while (used < 16 && first.max_value >= (1 << used)) ++used;
    if (used < bit_depth && used <= 12)
      s.note = "its 16-bit slices use at most " + std::to_string(used) + " bits (largest value " +
               std::to_string(first.max_value) + " in " + fs::path(files->front()).filename().string() + ", read as " +
               std::to_string(bit_depth) + "-bit): if that is the camera's depth, pass --bit-depth " + std::to_string(used);
  }
  s.read_region = [files, first, bit_depth](int z, const std::array<int, 4>& region, std::vector<std::uint8_t>& rgb) {
    const std::string& path = (*files)[static_cast<std::size_t>(z)];
    SliceFormat f;
    RgbImage img;
    try {
      img = read_slice(path, &f, bit_depth, region);
    } catch (const Error& e) {
      // a grey slice after a colour first slice is a mixed stack, and a
      // region beyond a slice smaller than the first one is that slice's size
      if (f.channels > 0 && f.channels != first.channels)
        throw Error(path, "has " + std::to_string(f.channels) + " channels, the first slice " +
                              fs::path(files->front()).filename().string() + " has " +
                              std::to_string(first.channels));
      if (f.nx > 0 && (f.nx != first.nx || f.ny != first.ny))
        throw Error(path, "slice is " + std::to_string(f.nx) + "x" + std::to_string(f.ny) + ", the first slice " +
                              fs::path(files->front()).filename().string() + " is " + std::to_string(first.nx) + "x" +
                              std::to_string(first.ny));
      throw;
    }
    if (f.nx != first.nx || f.ny != first.ny)
      throw Error(path, "slice is " + std::to_string(f.nx) + "x" + std::to_string(f.ny) + ", the first slice " +
                            fs::path(files->front()).filename().string() + " is " + std::to_string(first.nx) + "x" +
                            std::to_string(first.ny));
    if (f.channels != first.channels)
      throw Error(path, "has " + std::to_string(f.channels) + " channels, the first slice " +
                            fs::path(files->front()).filename().string() + " has " + std::to_string(first.channels));
    if (f.bits != first.bits)
      throw Error(path, "has " + std::to_string(f.bits) + "-bit pixels, the first slice " +
                            fs::path(files->front()).filename().string() + " has " + std::to_string(first.bits));
    rgb = std::move(img.rgb);
  };
  s.read = [region = s.read_region](int z, std::vector<std::uint8_t>& rgb) { region(z, {0, 0, 0, 0}, rgb); };
  return s;
}

SliceSource memory_source(std::vector<RgbImage> slices, std::string name) {
  if (slices.empty()) throw Error(name, "no slices");
  for (const auto& s : slices)
    if (s.nx != slices[0].nx || s.ny != slices[0].ny || s.rgb.size() != static_cast<std::size_t>(s.nx) * s.ny * 3)
      throw Error(name, "slices differ in size");
  auto data = std::make_shared<std::vector<RgbImage>>(std::move(slices));
  SliceSource s;
  s.nx = (*data)[0].nx;
  s.ny = (*data)[0].ny;
  s.nz = static_cast<int>(data->size());
  s.name = std::move(name);
  s.read = [data](int z, std::vector<std::uint8_t>& rgb) { rgb = (*data)[static_cast<std::size_t>(z)].rgb; };
  return s;
}

}  // namespace orthosim
