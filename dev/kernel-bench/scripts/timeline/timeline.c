// A CUDA injection library that writes a process's GPU timeline as CSV, for machines without Nsight Systems.
//
//   CUDA_INJECTION64_PATH=/path/libtimeline.so UMGEN_TIMELINE=out.csv umgen bench train ...
//
// The CUDA driver loads the library named by CUDA_INJECTION64_PATH at cuInit and calls its
// InitializeInjection, which turns on CUPTI's activity records: kernels (concurrent, each with its own
// start and end on the GPU), copies, memsets, driver API calls (when the host made them and how long they
// took) and synchronizations (where the host waited for the GPU). Records are written when CUPTI hands back
// a full buffer and at exit. One line a record; times are ns on CUPTI's clock, one clock for host and GPU:
//   K,start,end,stream,correlation,name      kernel
//   G,start,blocks,threads,correlation,name  the same kernel's launch size (grid blocks, threads a block)
//   M,start,end,stream,correlation,bytes     copy (kind in the name column: htod, dtoh, dtod, ...)
//   Z,start,end,stream,correlation,bytes     memset
//   A,start,end,thread,correlation,name      driver API call
//   S,start,end,stream,correlation,type      synchronization (event, stream wait, stream, context)
// dev/kernel-bench/scripts/timeline.sh builds it and reads the result (timeline.py).
#include <cupti.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define BUFFER_BYTES (16u << 20)

static FILE *out;

static void CUPTIAPI requested(uint8_t **buffer, size_t *size, size_t *max_records) {
    *buffer = aligned_alloc(8, BUFFER_BYTES);
    *size = *buffer ? BUFFER_BYTES : 0;
    *max_records = 0;
}

static const char *copy_kind(uint8_t kind) {
    switch (kind) {
        case CUPTI_ACTIVITY_MEMCPY_KIND_HTOD: return "htod";
        case CUPTI_ACTIVITY_MEMCPY_KIND_DTOH: return "dtoh";
        case CUPTI_ACTIVITY_MEMCPY_KIND_DTOD: return "dtod";
        default: return "other";
    }
}

static void CUPTIAPI completed(CUcontext ctx, uint32_t stream, uint8_t *buffer, size_t size, size_t valid) {
    (void)ctx, (void)stream, (void)size;
    CUpti_Activity *r = NULL;
    while (out && cuptiActivityGetNextRecord(buffer, valid, &r) == CUPTI_SUCCESS) {
        switch (r->kind) {
            case CUPTI_ACTIVITY_KIND_KERNEL:
            case CUPTI_ACTIVITY_KIND_CONCURRENT_KERNEL: {
                const CUpti_ActivityKernel10 *k = (const CUpti_ActivityKernel10 *)r;
                fprintf(out, "K,%llu,%llu,%u,%u,%.120s\n", (unsigned long long)k->start,
                        (unsigned long long)k->end, k->streamId, k->correlationId, k->name ? k->name : "?");
                fprintf(out, "G,%llu,%llu,%u,%u,%.120s\n", (unsigned long long)k->start,
                        (unsigned long long)k->gridX * k->gridY * k->gridZ, k->blockX * k->blockY * k->blockZ,
                        k->correlationId, k->name ? k->name : "?");
                break;
            }
            case CUPTI_ACTIVITY_KIND_MEMCPY: {
                const CUpti_ActivityMemcpy6 *m = (const CUpti_ActivityMemcpy6 *)r;
                fprintf(out, "M,%llu,%llu,%u,%u,%s %llu\n", (unsigned long long)m->start,
                        (unsigned long long)m->end, m->streamId, m->correlationId, copy_kind(m->copyKind),
                        (unsigned long long)m->bytes);
                break;
            }
            case CUPTI_ACTIVITY_KIND_MEMSET: {
                const CUpti_ActivityMemset4 *m = (const CUpti_ActivityMemset4 *)r;
                fprintf(out, "Z,%llu,%llu,%u,%u,%llu\n", (unsigned long long)m->start,
                        (unsigned long long)m->end, m->streamId, m->correlationId, (unsigned long long)m->bytes);
                break;
            }
            case CUPTI_ACTIVITY_KIND_DRIVER: {
                const CUpti_ActivityAPI *a = (const CUpti_ActivityAPI *)r;
                const char *name = "?";
                cuptiGetCallbackName(CUPTI_CB_DOMAIN_DRIVER_API, a->cbid, &name);
                fprintf(out, "A,%llu,%llu,%u,%u,%s\n", (unsigned long long)a->start,
                        (unsigned long long)a->end, a->threadId, a->correlationId, name);
                break;
            }
            case CUPTI_ACTIVITY_KIND_SYNCHRONIZATION: {
                const CUpti_ActivitySynchronization2 *s = (const CUpti_ActivitySynchronization2 *)r;
                fprintf(out, "S,%llu,%llu,%u,%u,%d\n", (unsigned long long)s->start,
                        (unsigned long long)s->end, s->streamId, s->correlationId, (int)s->type);
                break;
            }
            default:
                break;
        }
    }
    free(buffer);
}

static void finish(void) {
    cuptiActivityFlushAll(CUPTI_ACTIVITY_FLAG_FLUSH_FORCED);
    if (out) {
        fclose(out);
        out = NULL;
    }
}

int InitializeInjection(void) {
    const char *path = getenv("UMGEN_TIMELINE");
    out = fopen(path ? path : "timeline.csv", "w");
    if (!out) {
        perror("timeline: output");
        return 0;
    }
    const CUpti_ActivityKind kinds[] = {CUPTI_ACTIVITY_KIND_CONCURRENT_KERNEL, CUPTI_ACTIVITY_KIND_MEMCPY,
                                        CUPTI_ACTIVITY_KIND_MEMSET, CUPTI_ACTIVITY_KIND_DRIVER,
                                        CUPTI_ACTIVITY_KIND_SYNCHRONIZATION};
    if (cuptiActivityRegisterCallbacks(requested, completed) != CUPTI_SUCCESS) {
        fprintf(stderr, "timeline: cuptiActivityRegisterCallbacks failed\n");
        return 0;
    }
    for (size_t i = 0; i < sizeof kinds / sizeof kinds[0]; i++) {
        if (cuptiActivityEnable(kinds[i]) != CUPTI_SUCCESS) {
            fprintf(stderr, "timeline: activity kind %d not enabled\n", (int)kinds[i]);
        }
    }
    atexit(finish);
    return 1;
}
