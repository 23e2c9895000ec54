// Slice stacks: listing in natural order, decoding with checks, sources.
#include "libmodel/format/atomic.h"
#include "libmodel/segment/segment.h"
#include "libmodel/provenance.h"

#include <jpeglib.h>
#include <opencv2/core.hpp>
#include <opencv2/core/utils/logger.hpp>
#include <opencv2/imgcodecs.hpp>

#include <algorithm>
#include <array>
#include <cctype>
#include <csetjmp>
#include <cstdio>
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
    check_jpeg_data(path, b);
  }
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

std::string hash_stack(const std::string& dir) {
  std::string parts;
  for (const std::string& f : list_stack(dir)) {
    parts += fs::path(f).filename().string();
    parts += '\0';
    parts += hash_path(f);
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

RgbImage read_slice(const std::string& path, SliceFormat* format, int bit_depth) {
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
  cv::Mat m;
  try {
    const QuietCerr quiet;
    m = cv::imdecode(cv::Mat(1, static_cast<int>(bytes.size()), CV_8U, const_cast<std::uint8_t*>(bytes.data())),
                     cv::IMREAD_UNCHANGED);
  } catch (const cv::Exception& e) {
    throw Error(path, "cannot decode image (corrupt or unsupported)");
  }
  if (m.empty() || m.dims != 2 || m.rows <= 0 || m.cols <= 0)
    throw Error(path, "cannot decode image (corrupt, truncated or unsupported format)");
  SliceFormat f;
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
  if (format) *format = f;
  if (f.channels < 3)
    throw Error(path, "grey-scale image (" + std::to_string(f.channels) +
                          " channel" + (f.channels == 1 ? "" : "s") + "): segmentation needs colour slices");
  if (static_cast<std::int64_t>(f.nx) * f.ny > (std::int64_t(1) << 28))
    throw Error(path, "slice too large (more than 2^28 pixels)");
  RgbImage img;
  img.nx = f.nx;
  img.ny = f.ny;
  img.rgb.resize(static_cast<std::size_t>(f.nx) * f.ny * 3);
  const int ch = f.channels;
  const std::uint32_t full = (1u << bit_depth) - 1;  // the largest value of the significant bits
  std::int64_t grey = 0, total = 0;
  int max_value = 0;  // 16-bit slices only (the bit-depth note)
  for (int y = 0; y < f.ny; ++y) {
    std::uint8_t* dst = img.rgb.data() + static_cast<std::size_t>(y) * f.nx * 3;
    if (f.bits == 8) {
      const std::uint8_t* src = m.ptr<std::uint8_t>(y);
      for (int x = 0; x < f.nx; ++x) {  // OpenCV is BGR(A)
        dst[3 * x + 0] = src[ch * x + 2];
        dst[3 * x + 1] = src[ch * x + 1];
        dst[3 * x + 2] = src[ch * x + 0];
      }
    } else {
      const std::uint16_t* src = m.ptr<std::uint16_t>(y);
      for (int x = 0; x < f.nx; ++x)
        for (int c = 0; c < 3; ++c) {
          const std::uint32_t v = src[ch * x + 2 - c];
          max_value = std::max(max_value, static_cast<int>(v));
          dst[3 * x + c] = static_cast<std::uint8_t>(std::min<std::uint32_t>(255, (v * 255 + full / 2) / full));
        }
    }
    if (y % 4 == 0)
      for (int x = 0; x < f.nx; x += 4) {
        ++total;
        grey += dst[3 * x] == dst[3 * x + 1] && dst[3 * x + 1] == dst[3 * x + 2];
      }
  }
  if (format) format->max_value = max_value;
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
  s.read = [files, first, bit_depth](int z, std::vector<std::uint8_t>& rgb) {
    const std::string& path = (*files)[static_cast<std::size_t>(z)];
    SliceFormat f;
    RgbImage img;
    try {
      img = read_slice(path, &f, bit_depth);
    } catch (const Error& e) {
      // a grey slice after a colour first slice is a mixed stack
      if (f.channels > 0 && f.channels != first.channels)
        throw Error(path, "has " + std::to_string(f.channels) + " channels, the first slice " +
                              fs::path(files->front()).filename().string() + " has " +
                              std::to_string(first.channels));
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
