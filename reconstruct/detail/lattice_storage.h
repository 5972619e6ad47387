#pragma once
// Storage shared by the sparse block lattices of marching cubes
// (marching_cubes.cpp) and Deformed Marching Cubes (dmc.cpp). Internal to
// reconstruct/.
#include <cstddef>
#include <cstdint>
#include <memory>
#include <utility>
#include <vector>

namespace station::detail {

/// Set bits of a 64-bit mask. __builtin_popcountll without -mpopcnt (the x86-64
/// baseline has no POPCNT) is a call into libgcc, and the lattices count bits for
/// every vertex id; this is the same count inline (or the instruction when the
/// build targets it).
inline int popcount64(std::uint64_t x) {
#if defined(__POPCNT__) || !defined(__x86_64__)
  return __builtin_popcountll(x);
#else
  x = x - ((x >> 1) & 0x5555555555555555ULL);
  x = (x & 0x3333333333333333ULL) + ((x >> 2) & 0x3333333333333333ULL);
  x = (x + (x >> 4)) & 0x0F0F0F0F0F0F0F0FULL;
  return int((x * 0x0101010101010101ULL) >> 56);
#endif
}

/// A small open-addressing (linear probing) hash table from a packed 64-bit
/// block key to a block's index. Lookups are const and may run concurrently;
/// inserts may not (the lattices insert in their serial parts only). Which
/// slot a key lands in never changes the key -> index mapping, so results do
/// not depend on the table's history.
class BlockTable {
 public:
  static constexpr std::int32_t kAbsent = -1;

  /// `capacity`: initial slot count, a power of two.
  explicit BlockTable(std::size_t capacity = 1 << 12) { reset(capacity); }

  /// The index stored for `key`, or kAbsent.
  std::int32_t find(std::uint64_t key) const {
    for (std::size_t i = hash(key) & mask_;; i = (i + 1) & mask_) {
      if (slots_[i].second == kAbsent) return kAbsent;
      if (slots_[i].first == key) return slots_[i].second;
    }
  }

  /// The index stored for `key`; when there is none, stores `index` for it and
  /// sets `inserted` (grows the table at half load).
  std::int32_t find_or_insert(std::uint64_t key, std::int32_t index, bool& inserted) {
    std::size_t i = hash(key) & mask_;
    for (;; i = (i + 1) & mask_) {
      if (slots_[i].second == kAbsent) break;
      if (slots_[i].first == key) {
        inserted = false;
        return slots_[i].second;
      }
    }
    inserted = true;
    slots_[i] = {key, index};
    if (++count_ * 2 > slots_.size()) grow();
    return index;
  }

  std::size_t size() const { return count_; }

 private:
  static std::size_t hash(std::uint64_t k) {
    k ^= k >> 31;
    k *= 0x9E3779B97F4A7C15ULL;
    k ^= k >> 29;
    return std::size_t(k);
  }
  void reset(std::size_t capacity) {
    slots_.assign(capacity, {std::uint64_t(0), kAbsent});
    mask_ = capacity - 1;
  }
  void grow() {
    std::vector<std::pair<std::uint64_t, std::int32_t>> old;
    old.swap(slots_);
    reset(old.size() * 2);
    for (const auto& [key, index] : old) {
      if (index == kAbsent) continue;
      std::size_t i = hash(key) & mask_;
      while (slots_[i].second != kAbsent) i = (i + 1) & mask_;
      slots_[i] = {key, index};
    }
  }

  std::vector<std::pair<std::uint64_t, std::int32_t>> slots_;
  std::size_t mask_ = 0;
  std::size_t count_ = 0;
};

/// Vector in chunks of 4096: no copy when it grows (no transient doubling of
/// memory), and references stay valid.
template <class T>
class Chunked {
 public:
  static constexpr std::size_t kChunk = 4096;
  T& operator[](std::size_t i) { return chunks_[i / kChunk][i % kChunk]; }
  const T& operator[](std::size_t i) const { return chunks_[i / kChunk][i % kChunk]; }
  std::size_t size() const { return size_; }
  void push_back(const T& v) {
    if (size_ == chunks_.size() * kChunk) chunks_.emplace_back(new T[kChunk]);
    (*this)[size_++] = v;
  }
  /// Room for n more elements (serial), so that claim() may run in parallel.
  void reserve_more(std::size_t n) {
    while (chunks_.size() * kChunk < size_ + n) chunks_.emplace_back(new T[kChunk]);
  }
  /// Index of a new element, within the room made by reserve_more (parallel).
  std::size_t claim() { return __atomic_fetch_add(&size_, std::size_t(1), __ATOMIC_RELAXED); }
  void clear() {
    chunks_.clear();
    size_ = 0;
  }

 private:
  std::vector<std::unique_ptr<T[]>> chunks_;
  std::size_t size_ = 0;
};

}  // namespace station::detail
