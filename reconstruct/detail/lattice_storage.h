#pragma once
// Storage shared by the sparse block lattices of marching cubes
// (marching_cubes.cpp) and Deformed Marching Cubes (dmc.cpp). Internal to
// reconstruct/.
#include <algorithm>
#include <atomic>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <new>
#include <type_traits>
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
/// memory), and references stay valid. A chunk is allocated when its first element is
/// made, by the thread that makes it (claim() may run in parallel), and each element
/// is constructed where it is made: memory is first touched where it is used, and
/// room reserved for more claims than are made costs no memory. (First-touch page
/// faults are most of the cost of fresh memory on the VMs we measure on, about
/// 3 ms per MiB, and were taken serially here before: docs/dmc.md, "2026-12-06:
/// memory touched where it is used".) T must be trivially destructible.
template <class T>
class Chunked {
  static_assert(std::is_trivially_destructible_v<T>, "Chunked never runs destructors");

 public:
  static constexpr std::size_t kChunk = 4096;
  Chunked() = default;
  Chunked(const Chunked&) = delete;
  Chunked& operator=(const Chunked&) = delete;
  ~Chunked() { clear(); }
  T& operator[](std::size_t i) { return chunk(i / kChunk)[i % kChunk]; }
  const T& operator[](std::size_t i) const { return chunk(i / kChunk)[i % kChunk]; }
  std::size_t size() const { return size_; }
  /// Serial.
  void push_back(const T& v) {
    reserve_more(1);
    ::new (static_cast<void*>(made(size_))) T(v);
    ++size_;
  }
  /// Room for n more elements (serial), so that claim() may run in parallel: room in
  /// the chunk table only; the chunks come with their first element.
  void reserve_more(std::size_t n) {
    const std::size_t need = (size_ + n + kChunk - 1) / kChunk;
    if (need <= slots_) return;
    const std::size_t grown = std::max(need, 2 * slots_);
    std::unique_ptr<std::atomic<T*>[]> table(new std::atomic<T*>[grown]);
    for (std::size_t c = 0; c < grown; ++c)
      table[c].store(c < slots_ ? table_[c].load(std::memory_order_relaxed) : nullptr, std::memory_order_relaxed);
    table_ = std::move(table);
    slots_ = grown;
  }
  /// Index of a new element (value-initialised), within the room made by reserve_more
  /// (parallel).
  std::size_t claim() {
    const std::size_t i = __atomic_fetch_add(&size_, std::size_t(1), __ATOMIC_RELAXED);
    ::new (static_cast<void*>(made(i))) T();
    return i;
  }
  void clear() {
    for (std::size_t c = 0; c < slots_; ++c)
      if (T* p = table_[c].load(std::memory_order_relaxed)) ::operator delete(p, std::align_val_t(alignof(T)));
    table_.reset();
    slots_ = 0;
    size_ = 0;
  }

 private:
  T* chunk(std::size_t c) const { return table_[c].load(std::memory_order_acquire); }
  // Where element i goes, its chunk allocated when missing (two threads that both
  // find it missing race; one allocation is kept).
  T* made(std::size_t i) {
    std::atomic<T*>& slot = table_[i / kChunk];
    T* p = slot.load(std::memory_order_acquire);
    if (!p) {
      T* fresh = static_cast<T*>(::operator new(sizeof(T) * kChunk, std::align_val_t(alignof(T))));
      if (slot.compare_exchange_strong(p, fresh, std::memory_order_acq_rel, std::memory_order_acquire)) {
        p = fresh;
      } else {
        ::operator delete(fresh, std::align_val_t(alignof(T)));
      }
    }
    return p + i % kChunk;
  }

  std::unique_ptr<std::atomic<T*>[]> table_;
  std::size_t slots_ = 0;
  std::size_t size_ = 0;
};

}  // namespace station::detail
