// The one vector type of the cores: three coordinates, with the arithmetic the passes use.
// Vector3<double> is a position or a normal in computation (and in the decimation's position
// block); Vector3<float> is a stored point as read (the clustering's and the reorder's point
// blocks). Plain aggregates: their blocks are arrays of them.
#pragma once

#include <type_traits>

namespace sipmss::algorithms
{
template <class T>
struct Vector3
{
  T x, y, z;
  // Coordinate k (0, 1, 2).
  T operator[](int k) const { return k == 0 ? this->x : (k == 1 ? this->y : this->z); }
};
template <class T>
inline Vector3<T> operator-(const Vector3<T>& a, const Vector3<T>& b)
{
  return { a.x - b.x, a.y - b.y, a.z - b.z };
}
template <class T>
inline Vector3<T> operator+(const Vector3<T>& a, const Vector3<T>& b)
{
  return { a.x + b.x, a.y + b.y, a.z + b.z };
}
template <class T>
inline Vector3<T> operator*(T s, const Vector3<T>& a)
{
  return { s * a.x, s * a.y, s * a.z };
}
template <class T>
inline T Dot(const Vector3<T>& a, const Vector3<T>& b)
{
  return a.x * b.x + a.y * b.y + a.z * b.z;
}
template <class T>
inline Vector3<T> Cross(const Vector3<T>& a, const Vector3<T>& b)
{
  return { a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x };
}
using Vec3 = Vector3<double>;
using Float3 = Vector3<float>;
static_assert(sizeof(Vec3) == 24 && sizeof(Float3) == 12 && std::is_standard_layout_v<Vec3>,
  "vectors are packed coordinates (their blocks are arrays of them)");
} // namespace sipmss::algorithms
