// Viewer exports of quad grids: OBJ + MTL (written directly, quads kept) and
// glTF 2.0 through the assimp exporter.
#include "libmodel/format/atomic.h"
#include "libmodel/remesh/texture.h"

#include <assimp/Exporter.hpp>
#include <assimp/material.h>
#include <assimp/scene.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <memory>

namespace orthosim {

namespace {

// vertex (i, j) with i in 0..nu (i == nu: the seam again, u = 1)
struct SeamGrid {
  int nu, nv;
  int id(int i, int j) const { return j * (nu + 1) + i; }
};

}  // namespace

void write_quad_obj(const std::string& path, const QuadSurface& q, const std::string& mtl_file,
                    const std::string& material) {
  AtomicFile out(path);
  {
    std::FILE* f = std::fopen(out.temp().c_str(), "wb");
    if (!f) throw Error(path, "cannot write");
    std::fprintf(f, "# orthosim remesh: %d x %d quad grid (nu around x nv along), metres\n", q.nu, q.nv);
    if (!mtl_file.empty()) std::fprintf(f, "mtllib %s\n", mtl_file.c_str());
    for (Eigen::Index v = 0; v < q.vertices.rows(); ++v)
      std::fprintf(f, "v %.9g %.9g %.9g\n", q.vertices(v, 0), q.vertices(v, 1), q.vertices(v, 2));
    const SeamGrid g{q.nu, q.nv};
    for (int j = 0; j < q.nv; ++j) {
      const double v = q.uv.rows() ? q.uv(static_cast<Eigen::Index>(j) * q.nu, 1) : 0.0;
      for (int i = 0; i <= q.nu; ++i) std::fprintf(f, "vt %.9g %.9g\n", static_cast<double>(i) / q.nu, 1 - v);
    }
    if (!material.empty()) std::fprintf(f, "usemtl %s\n", material.c_str());
    for (int j = 0; j + 1 < q.nv; ++j)
      for (int i = 0; i < q.nu; ++i) {
        const int i1 = (i + 1) % q.nu;
        std::fprintf(f, "f %d/%d %d/%d %d/%d %d/%d\n", j * q.nu + i + 1, g.id(i, j) + 1, j * q.nu + i1 + 1,
                     g.id(i + 1, j) + 1, (j + 1) * q.nu + i1 + 1, g.id(i + 1, j + 1) + 1, (j + 1) * q.nu + i + 1,
                     g.id(i, j + 1) + 1);
      }
    const bool ok = std::ferror(f) == 0;
    if (std::fclose(f) != 0 || !ok) throw Error(path, "write failed");
  }
  out.commit();
}

void write_mtl(const std::string& path, const std::string& material, const std::string& texture_file) {
  std::string text = "# orthosim remesh\nnewmtl " + material + "\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nd 1\nillum 1\n";
  if (!texture_file.empty()) text += "map_Kd " + texture_file + "\n";
  write_text_file(path, text);
}

void write_gltf(const std::string& path, const QuadSurface& q, const std::string& texture_file,
                const std::string& name) {
  const SeamGrid g{q.nu, q.nv};
  const unsigned nverts = static_cast<unsigned>((q.nu + 1) * q.nv);
  const unsigned nfaces = static_cast<unsigned>(2 * q.nu * (q.nv - 1));
  auto scene = std::make_unique<aiScene>();
  scene->mRootNode = new aiNode();
  scene->mRootNode->mName = aiString(name);
  scene->mRootNode->mMeshes = new unsigned[1]{0};
  scene->mRootNode->mNumMeshes = 1;
  scene->mMaterials = new aiMaterial*[1];
  scene->mNumMaterials = 1;
  auto* mat = new aiMaterial();
  scene->mMaterials[0] = mat;
  aiString mname(name);
  mat->AddProperty(&mname, AI_MATKEY_NAME);
  aiColor4D white(1, 1, 1, 1);
  mat->AddProperty(&white, 1, AI_MATKEY_COLOR_DIFFUSE);
  if (!texture_file.empty()) {
    aiString tex(texture_file);
    mat->AddProperty(&tex, AI_MATKEY_TEXTURE_DIFFUSE(0));
  }
  scene->mMeshes = new aiMesh*[1];
  scene->mNumMeshes = 1;
  auto* mesh = new aiMesh();
  scene->mMeshes[0] = mesh;
  mesh->mName = aiString(name);
  mesh->mMaterialIndex = 0;
  mesh->mPrimitiveTypes = aiPrimitiveType_TRIANGLE;
  mesh->mNumVertices = nverts;
  mesh->mVertices = new aiVector3D[nverts];
  mesh->mTextureCoords[0] = new aiVector3D[nverts];
  mesh->mNumUVComponents[0] = 2;
  for (int j = 0; j < q.nv; ++j) {
    const double v = q.uv.rows() ? q.uv(static_cast<Eigen::Index>(j) * q.nu, 1) : 0.0;
    for (int i = 0; i <= q.nu; ++i) {
      const Eigen::Index r = static_cast<Eigen::Index>(j) * q.nu + (i % q.nu);
      mesh->mVertices[g.id(i, j)] = aiVector3D(static_cast<ai_real>(q.vertices(r, 0)),
                                               static_cast<ai_real>(q.vertices(r, 1)),
                                               static_cast<ai_real>(q.vertices(r, 2)));
      // assimp's convention is OpenGL's (origin bottom left); its glTF exporter flips v
      mesh->mTextureCoords[0][g.id(i, j)] = aiVector3D(static_cast<ai_real>(static_cast<double>(i) / q.nu),
                                                       static_cast<ai_real>(1 - v), 0);
    }
  }
  mesh->mNumFaces = nfaces;
  mesh->mFaces = new aiFace[nfaces];
  unsigned f = 0;
  auto tri = [&](int a, int b, int c) {
    aiFace& face = mesh->mFaces[f++];
    face.mNumIndices = 3;
    face.mIndices = new unsigned[3]{static_cast<unsigned>(a), static_cast<unsigned>(b), static_cast<unsigned>(c)};
  };
  for (int j = 0; j + 1 < q.nv; ++j)
    for (int i = 0; i < q.nu; ++i) {
      tri(g.id(i, j), g.id(i + 1, j), g.id(i + 1, j + 1));
      tri(g.id(i, j), g.id(i + 1, j + 1), g.id(i, j + 1));
    }
  Assimp::Exporter exporter;
  if (exporter.Export(scene.get(), "gltf2", path) != aiReturn_SUCCESS)
    throw Error(path, std::string("glTF export failed: ") + exporter.GetErrorString());
}

}  // namespace orthosim
