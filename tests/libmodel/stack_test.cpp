// Slice files read by region (read_slice's region, SliceSource::read_region):
// a region's pixels are the whole slice's, cut, in every format and layout
// the decoders take on (JPEG: baseline 4:2:0, 4:4:4, progressive, restart
// markers; PNG: 8-bit RGB and RGBA, 16-bit RGB and RGBA; TIFF: 8-bit RGB, LZW
// and uncompressed, 16-bit RGB and RGBA) and in those left to OpenCV (8-bit
// RGBA TIFF, BMP); the whole slice read is OpenCV's decoding; damage below a
// region is still refused where the format can tell (JPEG, PNG).
#include "libmodel/segment/segment.h"
#include "tests/test_util.h"

#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <array>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <random>
#include <string>
#include <vector>

using namespace orthosim;
namespace fs = std::filesystem;

namespace {

// A colour image with edges and texture (JPEG's chroma subsampling and its
// upsampler have something to do), of a size no iMCU divides.
cv::Mat test_image(int nx, int ny, int depth) {
  cv::Mat m(ny, nx, CV_MAKETYPE(depth, 3));
  std::mt19937 rng(7);
  std::uniform_int_distribution<int> noise(-20, 20);
  const double scale = depth == CV_16U ? 257.0 : 1.0;
  for (int y = 0; y < ny; ++y)
    for (int x = 0; x < nx; ++x) {
      const bool disc = (x - nx / 2) * (x - nx / 2) + (y - ny / 3) * (y - ny / 3) < nx * ny / 9;
      const int b = (disc ? 200 : 40) + noise(rng), g = (x * 255) / nx + noise(rng) / 2,
                r = ((x / 7 + y / 5) % 2 ? 180 : 90) + noise(rng);
      const int v[3] = {b, g, r};
      for (int c = 0; c < 3; ++c) {
        const double s = std::clamp(v[c], 0, 255) * scale + (depth == CV_16U ? (x + 3 * y + c) % 200 : 0);
        if (depth == CV_16U) m.at<cv::Vec<std::uint16_t, 3>>(y, x)[c] = static_cast<std::uint16_t>(std::min(65535.0, s));
        else m.at<cv::Vec3b>(y, x)[c] = static_cast<std::uint8_t>(s);
      }
    }
  return m;
}

// OpenCV's decoding of the file, converted as read_slice converts (BGR(A) to
// RGB, 16 bits to 8 from bit_depth 16)
std::vector<std::uint8_t> opencv_rgb(const std::string& path) {
  const cv::Mat m = cv::imread(path, cv::IMREAD_UNCHANGED);
  EXPECT_FALSE(m.empty()) << path;
  std::vector<std::uint8_t> out(static_cast<std::size_t>(m.rows) * m.cols * 3);
  const int ch = m.channels();
  for (int y = 0; y < m.rows; ++y)
    for (int x = 0; x < m.cols; ++x)
      for (int c = 0; c < 3; ++c) {
        const std::size_t at = (static_cast<std::size_t>(y) * m.cols + x) * 3 + c;
        if (m.depth() == CV_8U) out[at] = m.ptr<std::uint8_t>(y)[ch * x + 2 - c];
        else out[at] = static_cast<std::uint8_t>((m.ptr<std::uint16_t>(y)[ch * x + 2 - c] * 255u + 32767u) / 65535u);
      }
  return out;
}

std::vector<std::uint8_t> cut(const RgbImage& whole, const std::array<int, 4>& r) {
  std::vector<std::uint8_t> out;
  for (int y = r[1]; y < r[1] + r[3]; ++y) {
    const auto* row = whole.rgb.data() + (static_cast<std::size_t>(y) * whole.nx + r[0]) * 3;
    out.insert(out.end(), row, row + static_cast<std::size_t>(r[2]) * 3);
  }
  return out;
}

// read() throws Error naming `file` with `what` in its message.
void expect_error(const std::function<void()>& read, const std::string& file, const std::string& what) {
  try {
    read();
    ADD_FAILURE() << file << ": read, where it should have been refused with '" << what << "'";
  } catch (const Error& e) {
    EXPECT_EQ(e.file(), file);
    EXPECT_NE(std::string(e.what()).find(what), std::string::npos) << e.what();
  }
}

}  // namespace

TEST(SliceRegion, ARegionIsTheWholeSliceCutInEveryFormat) {
  test::TempDir d("stack-region");
  const int nx = 203, ny = 157;
  const cv::Mat m8 = test_image(nx, ny, CV_8U), m16 = test_image(nx, ny, CV_16U);
  cv::Mat m8a;
  cv::cvtColor(m8, m8a, cv::COLOR_BGR2BGRA);
  cv::Mat m16a;
  cv::cvtColor(m16, m16a, cv::COLOR_BGR2BGRA);
  for (int y = 0; y < ny; ++y)
    for (int x = 0; x < nx; ++x) {
      m8a.at<cv::Vec4b>(y, x)[3] = static_cast<std::uint8_t>(x + y);
      m16a.at<cv::Vec<std::uint16_t, 4>>(y, x)[3] = static_cast<std::uint16_t>(300 * x + y);
    }
  struct Case {
    std::string name;
    const cv::Mat* image;
    std::vector<int> params;
  };
  const std::vector<Case> cases = {
      {"baseline.jpg", &m8, {cv::IMWRITE_JPEG_QUALITY, 90}},  // 4:2:0
      {"full-chroma.jpg", &m8, {cv::IMWRITE_JPEG_LUMA_QUALITY, 90, cv::IMWRITE_JPEG_CHROMA_QUALITY, 80}},  // 4:4:4
      {"progressive.jpg", &m8, {cv::IMWRITE_JPEG_PROGRESSIVE, 1, cv::IMWRITE_JPEG_QUALITY, 75}},
      {"restarts.jpg", &m8, {cv::IMWRITE_JPEG_RST_INTERVAL, 3, cv::IMWRITE_JPEG_QUALITY, 60}},
      {"rgb8.png", &m8, {}},
      {"rgba8.png", &m8a, {cv::IMWRITE_PNG_COMPRESSION, 9}},
      {"rgb16.png", &m16, {}},
      {"rgba16.png", &m16a, {}},
      {"rgb8.tif", &m8, {}},  // LZW, 13-row strips
      {"rgb8-uncompressed.tif", &m8, {cv::IMWRITE_TIFF_COMPRESSION, 1}},
      {"rgb16.tif", &m16, {}},
      {"rgba16.tif", &m16a, {}},
      {"rgba8.tif", &m8a, {}},  // OpenCV's decoding, then the cut
      {"rgb8.bmp", &m8, {}},    // OpenCV's decoding, then the cut
  };
  const std::vector<std::array<int, 4>> regions = {
      {0, 0, nx, ny},  {0, 0, 1, 1},    {nx - 1, ny - 1, 1, 1}, {17, 33, 50, 41}, {nx - 37, 0, 37, ny},
      {0, ny - 20, nx, 20}, {101, 64, 1, 93}, {31, 9, 140, 1},   {16, 16, 32, 32}, {70, 110, 133, 47},
  };
  for (const Case& c : cases) {
    const std::string path = d / c.name;
    ASSERT_TRUE(cv::imwrite(path, *c.image, c.params)) << c.name;
    SliceFormat f;
    const RgbImage whole = read_slice(path, &f);
    ASSERT_EQ(whole.nx, nx) << c.name;
    ASSERT_EQ(whole.ny, ny) << c.name;
    EXPECT_EQ(f.nx, nx) << c.name;
    EXPECT_EQ(f.channels, c.name.rfind("rgba", 0) == 0 ? 4 : 3) << c.name;
    EXPECT_EQ(f.bits, c.name.find("16") != std::string::npos ? 16 : 8) << c.name;
    EXPECT_TRUE(whole.rgb == opencv_rgb(path)) << c.name << ": the whole slice is not OpenCV's decoding";
    for (const auto& r : regions) {
      SliceFormat fr;
      const RgbImage part = read_slice(path, &fr, 16, r);
      ASSERT_EQ(part.nx, r[2]) << c.name;
      ASSERT_EQ(part.ny, r[3]) << c.name;
      EXPECT_EQ(fr.nx, nx) << c.name;  // the whole slice's size
      EXPECT_EQ(fr.ny, ny) << c.name;
      EXPECT_EQ(fr.channels, f.channels) << c.name;
      EXPECT_TRUE(part.rgb == cut(whole, r))
          << c.name << ": region " << r[0] << "," << r[1] << "," << r[2] << "," << r[3] << " differs from the cut";
    }
    // a region beyond the slice: refused, naming the file, with its size said
    SliceFormat fb;
    expect_error([&] { read_slice(path, &fb, 16, {nx - 10, 0, 11, 5}); }, path,
                 "reaches beyond the slice, which is 203 x 157 px");
    EXPECT_EQ(fb.nx, nx) << c.name;
  }
}

// The stream below a region is read to its end: damage there is refused as
// it is for the whole slice (JPEG: its entropy codes; PNG: every chunk's CRC).
TEST(SliceRegion, DamageBelowTheRegionIsStillRefused) {
  test::TempDir d("stack-damage");
  const cv::Mat m = test_image(320, 240, CV_8U);
  const std::string jpg = d / "s.jpg", png = d / "s.png";
  ASSERT_TRUE(cv::imwrite(jpg, m, {cv::IMWRITE_JPEG_QUALITY, 95}));
  ASSERT_TRUE(cv::imwrite(png, m));
  const std::array<int, 4> top{10, 0, 100, 16};
  EXPECT_EQ(read_slice(jpg, nullptr, 16, top).rgb.size(), 100u * 16 * 3);
  // the JPEG cut after two thirds, its end marker put back
  const std::string bytes = test::read_file(jpg);
  test::write_file(jpg, bytes.substr(0, bytes.size() * 2 / 3) + "\xff\xd9");
  expect_error([&] { read_slice(jpg, nullptr, 16, top); }, jpg, "corrupt JPEG: premature end of data segment");
  // a PNG with a byte of its last image data changed
  std::string p = test::read_file(png);
  const std::size_t iend = p.rfind("IEND");
  ASSERT_NE(iend, std::string::npos);
  p[iend - 12] = static_cast<char>(p[iend - 12] ^ 0x55);  // inside the last IDAT's data, before its CRC
  test::write_file(png, p);
  expect_error([&] { read_slice(png, nullptr, 16, top); }, png, "corrupt PNG: CRC mismatch in chunk 'IDAT'");
}

// A stack source's region reads (what roi_source uses) give the cut slices,
// and a later slice of another size is said as such, not as a region beyond it.
TEST(SliceRegion, AStacksRegionReadsAreItsSlicesCut) {
  test::TempDir d("stack-source");
  const cv::Mat m = test_image(120, 90, CV_8U);
  fs::create_directories(d / "s");
  ASSERT_TRUE(cv::imwrite(d / "s/a0.png", m));
  ASSERT_TRUE(cv::imwrite(d / "s/a1.jpg", m, {cv::IMWRITE_JPEG_QUALITY, 90}));
  cv::Mat small;
  cv::resize(m, small, cv::Size(60, 45));
  ASSERT_TRUE(cv::imwrite(d / "s/a2.png", small));
  const SliceSource s = stack_source(d / "s");
  ASSERT_TRUE(static_cast<bool>(s.read_region));
  for (int z = 0; z < 2; ++z) {
    std::vector<std::uint8_t> whole, part;
    s.read(z, whole);
    s.read_region(z, {50, 40, 70, 50}, part);
    RgbImage w;
    w.nx = 120, w.ny = 90, w.rgb = whole;
    EXPECT_TRUE(part == cut(w, {50, 40, 70, 50})) << "slice " << z;
  }
  std::vector<std::uint8_t> part;
  expect_error([&] { s.read_region(2, {50, 40, 70, 50}, part); }, d / "s/a2.png",
               "slice is 60x45, the first slice a0.png is 120x90");
}

// A stack's hash (pipeline's cache key, segment's provenance) is of what
// segment reads: every file's name (they number the slices), the first file
// (the stack's format) and the slices of --slices, not the others.
TEST(SliceRegion, AStacksHashIsOfTheSlicesSegmentReads) {
  test::TempDir d("stack-hash");
  fs::create_directories(d / "s");
  const cv::Mat m = test_image(40, 30, CV_8U);
  for (int z = 0; z < 4; ++z) ASSERT_TRUE(cv::imwrite(d / ("s/a" + std::to_string(z) + ".png"), m + cv::Scalar::all(z)));
  const std::string dir = d / "s";
  const std::string all = hash_stack(dir), part = hash_stack(dir, 2, 3), tail = hash_stack(dir, 2);
  EXPECT_EQ(part, tail);
  EXPECT_NE(all, part);
  EXPECT_EQ(hash_stack(dir, 0, -1), all);
  // a slice outside the range: the whole stack's hash changes, the range's does not
  ASSERT_TRUE(cv::imwrite(d / "s/a1.png", m + cv::Scalar::all(9)));
  EXPECT_NE(hash_stack(dir), all);
  EXPECT_EQ(hash_stack(dir, 2, 3), part);
  // a slice in the range, the first file (the stack's format) and a name: both change
  for (const char* f : {"a3.png", "a0.png"}) {
    const std::string before = hash_stack(dir, 2, 3);
    ASSERT_TRUE(cv::imwrite(d / (std::string("s/") + f), m + cv::Scalar::all(20)));
    EXPECT_NE(hash_stack(dir, 2, 3), before) << f;
  }
  const std::string before = hash_stack(dir, 2, 3);
  fs::rename(d / "s/a1.png", d / "s/a1b.png");
  EXPECT_NE(hash_stack(dir, 2, 3), before);
}
